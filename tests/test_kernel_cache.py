"""The compiled kernels' cache is emptied when the package's sources change (``linereg._kernel_cache``)."""

import os
from pathlib import Path

from linereg._kernel_cache import STAMP, clear_stale, fingerprint


def _package(root: Path) -> Path:
    package = root / "pkg"
    (package / "sub" / "__pycache__").mkdir(parents=True)
    (package / "__pycache__").mkdir()
    (package / "a.py").write_text("x = 1\n")
    (package / "sub" / "b.py").write_text("y = 2\n")
    return package


def _cached(package: Path) -> list[Path]:
    files = [
        package / "__pycache__" / "a.f-1.py311.nbi",
        package / "__pycache__" / "a.f-1.py311.1.nbc",
        package / "sub" / "__pycache__" / "b.g-3.py311.nbi",
    ]
    for f in files:
        f.write_bytes(b"kernel")
    return files


def test_a_cache_filled_under_other_sources_is_emptied_once(tmp_path):
    package = _package(tmp_path)
    assert clear_stale(package)  # no stamp yet: whatever is cached came from sources it cannot vouch for
    files = _cached(package)
    keep = package / "__pycache__" / "a.cpython-311.pyc"
    keep.write_bytes(b"bytecode")
    assert not clear_stale(package)  # the same sources: the kernels stay
    assert all(f.exists() for f in files)
    # one module edited (another module's kernels may have inlined its kernels): every kernel goes
    b = package / "sub" / "b.py"
    os.utime(b, ns=(b.stat().st_atime_ns, b.stat().st_mtime_ns + 10**9))
    assert clear_stale(package)
    assert not any(f.exists() for f in files)
    assert keep.exists()  # Python's own bytecode is Python's business
    assert (package / "__pycache__" / STAMP).read_text() == fingerprint(package)
    assert not clear_stale(package)


def test_a_new_module_changes_the_fingerprint(tmp_path):
    package = _package(tmp_path)
    before = fingerprint(package)
    (package / "c.py").write_text("z = 3\n")
    assert fingerprint(package) != before


def test_a_package_it_cannot_write_to_is_left_alone(tmp_path):
    package = _package(tmp_path)
    files = _cached(package)
    os.chmod(package / "__pycache__", 0o500)
    os.chmod(package / "sub" / "__pycache__", 0o500)
    try:
        if os.access(package / "__pycache__", os.W_OK):  # root ignores permissions: nothing to test
            return
        assert not clear_stale(package)
        assert all(f.exists() for f in files)
    finally:
        os.chmod(package / "__pycache__", 0o700)
        os.chmod(package / "sub" / "__pycache__", 0o700)
