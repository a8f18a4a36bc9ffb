"""Files that are not what they should be: non-UTF-8 text, a directory where a file belongs."""

import json

import pytest

from robust_imdp.cli import main
from robust_imdp.errors import ProblemFileError
from robust_imdp.io.files import load_problem, load_result, parse_problem_file, read_data_file
from problem_texts import ONE_D_TEMPLATE as TOML


CSV = "x_1,u,x_next_1\n0.5,a,1.25\n1.5,a,1.75\n"


def test_a_non_utf8_problem_file_names_the_file_line_and_column(tmp_path):
    # "# Zürich" in Latin-1 on line 3: 0xfc is byte 4 of that line
    text = TOML.format(data="d.csv").replace("upper = [4.0]\n", "upper = [4.0]\n# Z\u00fcrich\n")
    p = tmp_path / "p.toml"
    p.write_bytes(text.encode("latin-1"))
    with pytest.raises(ProblemFileError,
                       match=r"problem file .*p\.toml: line 4, column 4: not UTF-8 text \(byte 0xfc\); save the file as UTF-8"):
        parse_problem_file(p)


def test_a_non_utf8_csv_names_the_file_line_and_column(tmp_path):
    # the mode name "caf\xe9" (Latin-1) on line 3, column 9 (after "1.5,caf")
    (tmp_path / "d.csv").write_bytes((CSV.replace("1.5,a,", "1.5,caf\u00e9,")).encode("latin-1"))
    with pytest.raises(ProblemFileError, match=r"data file .*d\.csv: line 3, column 8: not UTF-8 text \(byte 0xe9\)"):
        read_data_file(tmp_path / "d.csv")


def test_a_directory_as_the_data_file_names_the_key_and_says_a_file_was_expected(tmp_path):
    (tmp_path / "data.csv").mkdir()
    (tmp_path / "p.toml").write_text(TOML.format(data="data.csv"))
    with pytest.raises(ProblemFileError, match=r"\[data\]\.path in .*p\.toml: .*data\.csv is a directory; expected a "
                                               r"data file \(\.csv or \.npz\)"):
        load_problem(tmp_path / "p.toml")
    (tmp_path / "p.toml").write_text(TOML.format(data="."))  # no suffix at all: the same message
    with pytest.raises(ProblemFileError, match=r"\[data\]\.path in .*p\.toml: .* is a directory; expected a data file"):
        load_problem(tmp_path / "p.toml")


def test_a_directory_as_the_problem_file(tmp_path):
    (tmp_path / "p.toml").mkdir()
    with pytest.raises(ProblemFileError, match=r"problem file .*p\.toml is a directory; expected a TOML problem file"):
        parse_problem_file(tmp_path / "p.toml")


def test_a_non_utf8_result_file(tmp_path):
    doc = json.dumps({"format": "robust_imdp.result/1", "formula": "F caf\u00e9"}, ensure_ascii=False)
    (tmp_path / "result.json").write_bytes(doc.encode("latin-1"))
    with pytest.raises(ProblemFileError, match=r"result file .*result\.json: line 1, column \d+: not UTF-8 text"):
        load_result(tmp_path)


@pytest.mark.parametrize("case", ["latin1_toml", "latin1_csv", "directory"])
def test_the_command_prints_one_line_naming_the_file(tmp_path, capsys, case):
    data = "d.csv"
    text = TOML.format(data=data)
    (tmp_path / "d.csv").write_text(CSV)
    if case == "latin1_toml":
        (tmp_path / "p.toml").write_bytes(text.replace('formula = "F des"', 'formula = "F des" # \u00e9').encode("latin-1"))
        want = "p.toml: line 9, column 21: not UTF-8 text (byte 0xe9)"
    elif case == "latin1_csv":
        (tmp_path / "p.toml").write_text(text)
        (tmp_path / "d.csv").write_bytes(CSV.replace("0.5,a", "0.5\u00e9,a").encode("latin-1"))
        want = "d.csv: line 2, column 4: not UTF-8 text (byte 0xe9)"
    else:
        (tmp_path / "d.csv").unlink()
        (tmp_path / "d.csv").mkdir()
        (tmp_path / "p.toml").write_text(text)
        want = "d.csv is a directory; expected a data file (.csv or .npz)"
    code = main(["run", str(tmp_path / "p.toml"), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1, err
    assert err.startswith("robust-imdp: error: ") and want in err and len(err.strip().splitlines()) == 1
    assert "codec" not in err and "Is a directory" not in err
