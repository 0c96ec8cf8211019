"""
The one writer of benchmark results: ``bench/results/<name>.json`` with honest goals.

Every benchmark builds its goals with :func:`goal` (``met`` is computed from the measured
value, never typed in) and writes them with :func:`write_report`, which adds machine facts.
"""

from __future__ import annotations

import datetime
import json
import math
import os
from pathlib import Path
import platform
import sys
from typing import Any, Dict, List, Optional

__all__ = ['goal', 'write_report', 'results_dir']

_COMPARE = {
    '<': lambda v, t: v < t,
    '<=': lambda v, t: v <= t,
    '>': lambda v, t: v > t,
    '>=': lambda v, t: v >= t,
    '==': lambda v, t: v == t,
}


def goal(metric: str, target: float, comparison: str, value: float) -> Dict[str, Any]:
    """
    One goal entry; ``met`` is ``value <comparison> target`` (False for NaN values).

    :param metric: what is measured, with its unit (e.g. ``'bad2_ratio_vs_sgbm'``).
    :param target: the goal's threshold.
    :param comparison: one of ``<``, ``<=``, ``>``, ``>=``, ``==``.
    :param value: the measured value.
    """
    if comparison not in _COMPARE:
        raise ValueError(f'comparison must be one of {sorted(_COMPARE)}, got {comparison!r}')
    value = float(value)
    met = (not math.isnan(value)) and bool(_COMPARE[comparison](value, float(target)))
    return {'metric': metric, 'target': target, 'comparison': comparison, 'value': value,
            'met': met}


def results_dir() -> Path:
    """``bench/results`` of this source tree (or ``$STEREO_MANIP_BENCH_RESULTS``)."""
    env = os.environ.get('STEREO_MANIP_BENCH_RESULTS')
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / 'bench').is_dir() and (parent / 'msgs').is_dir():
            return parent / 'bench' / 'results'
    return Path.cwd() / 'bench' / 'results'


def _machine() -> Dict[str, Any]:
    info: Dict[str, Any] = {
        'python': sys.version.split()[0],
        'platform': platform.platform(),
        'cpu_count': os.cpu_count(),
    }
    for mod in ('numpy', 'scipy', 'cv2', 'open3d', 'numba'):
        m = sys.modules.get(mod)
        if m is not None:
            info[mod] = getattr(m, '__version__', '?')
    return info


def write_report(name: str, goals: List[Dict[str, Any]], *, directory: Optional[Path] = None,
                 **raw: Any) -> Path:
    """
    Write ``<directory>/<name>.json`` with goals, raw figures and machine facts; print a table.

    :param name: benchmark name, starting with its component (``stereo_middlebury``).
    :param goals: entries made by :func:`goal`.
    :param raw: any JSON-serialisable raw figures (numpy scalars/arrays are converted).
    :returns: the path written.
    """
    out_dir = Path(directory) if directory is not None else results_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    report = {
        'name': name,
        'date': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
        'machine': _machine(),
        'goals': goals,
        **raw,
    }
    path = out_dir / f'{name}.json'
    path.write_text(json.dumps(report, indent=2, default=_to_json) + '\n')
    print(f'{name}: wrote {path}')
    for g in goals:
        mark = 'MET ' if g['met'] else 'MISS'
        print(f"  [{mark}] {g['metric']}: {g['value']:.6g} {g['comparison']} {g['target']}")
    return path


def _to_json(obj: Any) -> Any:
    try:
        import numpy as np
    except ImportError:  # pragma: no cover
        np = None
    if np is not None:
        if isinstance(obj, np.ndarray):
            return obj.tolist()
        if isinstance(obj, np.generic):
            return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f'not JSON serialisable: {type(obj).__name__}')
