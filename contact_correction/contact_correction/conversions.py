"""
ContactState / ContactPair messages from correction results (the shared conversions lack them).

Message <-> array only; no rclpy node code.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from std_msgs.msg import Header
from stereo_manip_msgs.msg import ContactElement, ContactPair as ContactPairMsg, ContactState

from stereo_manip_tools.conversions import numpy_to_point, numpy_to_vector3

from .contact_relation import ContactPair
from .correction import CorrectionResult

__all__ = ['contact_state_msg', 'contact_pairs_msgs']


def contact_pairs_msgs(pairs: Sequence[ContactPair], points: np.ndarray, normals: np.ndarray,
                       distances: np.ndarray) -> list:
    """Make the ContactPair messages (fixed-object frame quantities) of a relation."""
    out = []
    for k, p in enumerate(pairs):
        m = ContactPairMsg()
        m.moving = ContactElement(type=int(p.moving_type), index=int(p.moving_index))
        m.fixed = ContactElement(type=int(p.fixed_type), index=int(p.fixed_index))
        m.point = numpy_to_point(points[k])
        m.normal = numpy_to_vector3(normals[k])
        m.distance = float(distances[k])
        out.append(m)
    return out


def contact_state_msg(result: CorrectionResult, header: Header, moving_object: str,
                      fixed_object: str) -> ContactState:
    """
    Make the ContactState of one corrected (or passed-through) frame.

    :param header: stamp of the observation; frame_id = the fixed object's frame.
    """
    msg = ContactState(header=header, moving_object=moving_object, fixed_object=fixed_object)
    g = result.geometry
    if g is not None and len(result.pairs):
        msg.pairs = contact_pairs_msgs(result.pairs, g.points, g.normals, g.distances)
    d = result.directions
    if d is not None:
        msg.rotation_rank = int(d.rotation_rank)
        msg.constraint_rank = int(d.constraint_rank)
        msg.constrained_translation = [numpy_to_vector3(v) for v in d.constrained_translation]
        msg.free_translation = [numpy_to_vector3(v) for v in d.free_translation]
        msg.constrained_rotation = [numpy_to_vector3(v) for v in d.constrained_rotation]
        msg.free_rotation = [numpy_to_vector3(v) for v in d.free_rotation]
    msg.penetration_depth = float(result.penetration_before)
    msg.max_contact_residual = float(result.max_residual)
    msg.corrected = bool(result.corrected)
    msg.status = result.status
    return msg
