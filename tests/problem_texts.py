"""Problem-file texts shared by the file-handling tests (cache, CLI, file errors)."""

# A 1-D problem: one affine mode, uniform noise, "F des"; the data file name is a template field.
ONE_D_TEMPLATE = """[space]
lower = [0.0]
upper = [4.0]
cell_size = [0.25]
[[regions.des]]
lower = [2.0]
upper = [3.0]
[spec]
formula = "F des"
threshold = 0.9
[data]
path = "{data}"
[modes.a]
A = [[0.5]]
b = [1.0]
[noise]
kind = "uniform"
bound = [0.01]
[learning]
rkhs_bound = 1.0
"""

ONE_D = ONE_D_TEMPLATE.format(data="d.csv")
