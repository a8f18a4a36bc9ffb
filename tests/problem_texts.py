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


def write_one_d(folder, name: str = "p.toml"):
    """Write the 1-D problem (``ONE_D``) and its data ``d.csv`` into ``folder``; return the problem file.

    x+ = 0.5 x + 1 + 0.1 sin(x) + v: 16 cells, 30 points (seed 0), contracting towards x = 2.2 inside
    des = [2, 3].
    """
    import numpy as np

    rng = np.random.default_rng(0)
    x = rng.uniform(0, 4, 30)
    xn = 0.5 * x + 1 + 0.1 * np.sin(x) + rng.uniform(-0.01, 0.01, 30)
    (folder / "d.csv").write_text("x_1,u,x_next_1\n" + "".join(f"{a:.17g},a,{b:.17g}\n" for a, b in zip(x, xn)))
    (folder / name).write_text(ONE_D)
    return folder / name
