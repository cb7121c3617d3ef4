"""The benchmarks' memory sampler sees processes this one did not start itself (a fork server's workers)."""

import subprocess
import sys

import pytest

from linereg.bench.memory import PeakMemory

ALLOCATE = "import sys, numpy; a = numpy.ones(60 * 2**17); print('ready', flush=True); sys.stdin.read()"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_peak_of_a_grandchild_is_measured():
    # a grandchild, as a fork server's worker is: resource.RUSAGE_CHILDREN never counts it
    middle = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {ALLOCATE!r}])"
    peak = PeakMemory(interval_s=60.0)  # sampled by hand below, no timing involved
    with subprocess.Popen(
        [sys.executable, "-c", middle], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    ) as child:
        assert child.stdout is not None and child.stdout.readline().startswith(b"ready")
        peak.sample()
        child.communicate(b"")
    result = peak.result()
    assert result["children"] >= 2 and result["largest_child_mb"] >= 60
    assert result["tree_mb"] >= result["largest_child_mb"]
