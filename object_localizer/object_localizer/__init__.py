"""
Known 3D models localised in point clouds.

Descriptors + RANSAC, then ICP with an M-estimator; 6-DOF pose tracking.

Importing this package keeps Open3D's Plotly/Dash web viewer out of the process (when Open3D
is not imported yet): ``import open3d`` loads ``open3d.visualization.draw_plotly``, which
imports dash, plotly, IPython, requests and werkzeug -- measured 0.4-0.8 s of CPU and 2-3 s
of wall time on the shared 2-core machine, a third of the localizer node's imports, for
functions this package never calls. Its three functions raise ImportError here instead.
"""

import sys as _sys
import types as _types


def _no_plotly(*args, **kwargs):
    raise ImportError('open3d.visualization.draw_plotly is not loaded by object_localizer '
                      '(import open3d before object_localizer to use it)')


if 'open3d' not in _sys.modules and 'open3d.visualization.draw_plotly' not in _sys.modules:
    _stub = _types.ModuleType('open3d.visualization.draw_plotly')
    _stub.get_plotly_fig = _stub.draw_plotly = _stub.draw_plotly_server = _no_plotly
    _sys.modules['open3d.visualization.draw_plotly'] = _stub
