"""retain_freed_memory: a worker thread's per-frame arrays reuse pages instead of faulting."""

import subprocess
import sys

import pytest
from stereo_manip_tools.memory import MMAP_THRESHOLD_MAX, retain_freed_memory

# A stereo-node-like frame on a worker thread (its own malloc arena): four 640x480 float32
# temporaries allocated and freed per frame; prints the minor page faults per frame.
_FRAMES = r"""
import resource, sys, threading
import numpy as np
if sys.argv[1] == 'retain':
    from stereo_manip_tools.memory import retain_freed_memory
    assert retain_freed_memory()
out = []
def run():
    def frame():
        a = np.ones((480, 640), np.float32)
        b = a + np.float32(1.0)
        c = np.sqrt(b)
        return float(np.where(c > 1, c, 0).astype(np.float32).sum())
    for _ in range(3):
        frame()
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        frame()
    out.append((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0) / 20)
t = threading.Thread(target=run)
t.start()
t.join()
print(out[0])
"""


def _faults_per_frame(mode: str) -> float:
    res = subprocess.run([sys.executable, '-c', _FRAMES, mode], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    return float(res.stdout.split()[-1])


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='glibc allocator only')
def test_retained_memory_removes_the_page_faults_of_a_frame():
    default = _faults_per_frame('default')
    retained = _faults_per_frame('retain')
    # 4 arrays x 1.2 MB = ~1200 pages: by default most are faulted in again every frame
    assert default > 300, f'{default} faults per frame without retaining: test is not probing'
    assert retained < 0.05 * default, (retained, default)


def test_thresholds_out_of_range_are_rejected():
    with pytest.raises(ValueError, match='mmap_threshold'):
        retain_freed_memory(mmap_threshold=MMAP_THRESHOLD_MAX + 1)
    with pytest.raises(ValueError, match='mmap_threshold'):
        retain_freed_memory(mmap_threshold=0)
    with pytest.raises(ValueError, match='trim_threshold'):
        retain_freed_memory(trim_threshold=1 << 31)
