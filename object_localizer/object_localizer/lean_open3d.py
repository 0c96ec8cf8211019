"""
Keep Open3D's Plotly/Dash web viewer out of the node process (import before Open3D).

``import open3d`` loads ``open3d.visualization.draw_plotly``, which imports dash, plotly,
IPython, requests and werkzeug -- measured 0.4-0.8 s of CPU and 2-3 s of wall time on the shared
2-core machine, a third of the localizer node's imports, for functions the node never calls.
Importing this module first (only ``localizer_node`` does: a library import must not change
Open3D for its caller) puts a stub in its place whose three functions raise ImportError.
"""

import sys
import types


def _no_plotly(*args, **kwargs):
    raise ImportError('open3d.visualization.draw_plotly is not loaded in the object_localizer '
                      'node process')


if 'open3d' not in sys.modules and 'open3d.visualization.draw_plotly' not in sys.modules:
    _stub = types.ModuleType('open3d.visualization.draw_plotly')
    _stub.get_plotly_fig = _stub.draw_plotly = _stub.draw_plotly_server = _no_plotly
    sys.modules['open3d.visualization.draw_plotly'] = _stub
