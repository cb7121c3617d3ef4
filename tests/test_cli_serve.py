"""``linereg serve`` refuses a wrong --map in one line, before starting workers or a zenoh session."""

import pytest

from linereg.cli import main


@pytest.mark.parametrize(
    ("name", "content", "problem"),
    [("maps", "dir", "is a directory"), ("none.linemap", None, "no such map file"),
     ("noise.linemap", b"\x00garbage" * 10, "not a linereg map file")],
)  # fmt: skip
def test_serve_checks_the_map_file_first(tmp_path, capsys, name, content, problem):
    path = tmp_path / name
    if content == "dir":
        path.mkdir()
    elif content is not None:
        path.write_bytes(content)
    code = main(["serve", "--map", str(path), "--listen", "tcp/127.0.0.1:1"])  # would fail to listen
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f"linereg serve: error: {path}: {problem}")
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
