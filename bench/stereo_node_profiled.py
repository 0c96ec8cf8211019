#!/usr/bin/env python3
"""
``stereo_depth_node`` with CPU accounting per stage, for ``bench/stereo_node_cpu.py`` (part 1b).

Runs the node's own ``main()`` after wrapping the functions its worker calls per frame
(decoding, census, fused kernel, left-right check, speckle filter, median, fill, depth, cloud
packing, PointCloud2 wrapping, publishing) and its subscription callbacks: each call records
the process CPU time (all threads: numba's kernels run on the workqueue thread) and the
calling thread's CPU time. At exit the medians per call go to the JSON file named by
``STEREO_PROFILE_OUT``. Run as the node (``python bench/stereo_node_profiled.py --ros-args
...``); the wrappers cost ~10 us per call.
"""

from __future__ import annotations

import atexit
import json
import os
import threading
import time
from typing import Any, Callable, Dict, List, Tuple

import numpy as np
from stereo_depth import optimization as op, pipeline as pl, stereo_depth_node as sn

_RECORDS: Dict[str, List[Tuple[float, float]]] = {}
_LOCK = threading.Lock()


def timed(name: str, f: Callable) -> Callable:
    """Wrap ``f``: each call records (process CPU ms, thread CPU ms) under ``name``."""
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        p0, t0 = time.process_time(), time.thread_time()
        try:
            return f(*args, **kwargs)
        finally:
            p1, t1 = time.process_time(), time.thread_time()
            with _LOCK:
                _RECORDS.setdefault(name, []).append((1e3 * (p1 - p0), 1e3 * (t1 - t0)))
    return wrapper


def dump() -> None:
    """Write median / p95 / max per stage (process and thread CPU, ms per call)."""
    out = {}
    with _LOCK:
        records = {k: list(v) for k, v in _RECORDS.items()}
    for name, rec in records.items():
        a = np.asarray(rec, float)[3:] if len(rec) > 6 else np.asarray(rec, float)  # warm-up
        out[name] = {'calls': int(a.shape[0]),
                     'process_cpu_ms': {'median': float(np.median(a[:, 0])),
                                        'p95': float(np.percentile(a[:, 0], 95)),
                                        'max': float(a[:, 0].max())},
                     'thread_cpu_ms': {'median': float(np.median(a[:, 1])),
                                       'p95': float(np.percentile(a[:, 1], 95)),
                                       'max': float(a[:, 1].max())}}
    with open(os.environ['STEREO_PROFILE_OUT'], 'w') as f:
        json.dump(out, f, indent=1)


def main() -> None:
    """Wrap the stages and run the node."""
    for mod, names in ((sn, ('prepare_pair', 'compute_disparity', 'disparity_to_depth',
                             'cloud_message_data', 'float32_fields_to_pointcloud2')),
                       (pl, ('census_block_matching', 'left_right_check', 'remove_speckles',
                             'median_filter', 'fill_invalid')),
                       (op, ('census_planes', '_census_box_wta'))):
        for n in names:
            setattr(mod, n, timed(f"{mod.__name__.rsplit('.', 1)[-1]}.{n}", getattr(mod, n)))
    for n in ('_on_image', '_on_info', '_process'):
        setattr(sn.StereoDepthNode, n, timed(f'node.{n}', getattr(sn.StereoDepthNode, n)))
    init = sn.StereoDepthNode.__init__

    def init_timed(self, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        self.pub_points.publish = timed('publish points2', self.pub_points.publish)

    sn.StereoDepthNode.__init__ = init_timed
    atexit.register(dump)
    sn.main()


if __name__ == '__main__':
    main()
