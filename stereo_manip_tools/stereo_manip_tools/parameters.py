"""
ParameterDescriptor builders and input QoS choices shared by every node.

Every node declares each parameter with a description, a range and read-only where it must be;
these helpers keep those declarations short and identical across packages.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping, Optional, Sequence

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, \
    ParameterType, SetParametersResult
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy

__all__ = ['float_descriptor', 'int_descriptor', 'string_descriptor', 'bool_descriptor',
           'INPUT_QOS_CHOICES', 'input_qos_descriptor', 'input_qos_profile',
           'choice_parameter_reason', 'nonfinite_parameter_reason', 'reject_nonfinite_parameters']


def float_descriptor(description: str, low: float, high: float,
                     read_only: bool = False) -> ParameterDescriptor:
    """Describe a double parameter in ``[low, high]``."""
    return ParameterDescriptor(type=ParameterType.PARAMETER_DOUBLE, description=description,
                               read_only=read_only,
                               floating_point_range=[FloatingPointRange(
                                   from_value=float(low), to_value=float(high))])


def int_descriptor(description: str, low: int, high: int,
                   read_only: bool = False) -> ParameterDescriptor:
    """Describe an integer parameter in ``[low, high]`` (step 1)."""
    return ParameterDescriptor(type=ParameterType.PARAMETER_INTEGER, description=description,
                               read_only=read_only,
                               integer_range=[IntegerRange(from_value=int(low),
                                                           to_value=int(high), step=1)])


def string_descriptor(description: str, read_only: bool = False,
                      additional_constraints: str = '') -> ParameterDescriptor:
    """
    Describe a string parameter (validate its value in the node's on-set callback).

    :param additional_constraints: free text shown by ``ros2 param describe`` (e.g. the
        allowed values).
    """
    return ParameterDescriptor(type=ParameterType.PARAMETER_STRING, description=description,
                               read_only=read_only,
                               additional_constraints=additional_constraints)


def bool_descriptor(description: str, read_only: bool = False) -> ParameterDescriptor:
    """Describe a boolean parameter."""
    return ParameterDescriptor(type=ParameterType.PARAMETER_BOOL, description=description,
                               read_only=read_only)


INPUT_QOS_CHOICES = ('sensor_data', 'reliable')


def input_qos_descriptor(topic: str) -> ParameterDescriptor:
    """Describe the read-only ``input_qos`` parameter of a node taking large messages."""
    return ParameterDescriptor(
        type=ParameterType.PARAMETER_STRING, read_only=True,
        description=f'QoS of the {topic} subscription: sensor_data (best effort, REP 2003) or '
                    'reliable (keep last few; lossless for multi-megabyte messages, which '
                    'best-effort DDS drops whole when one fragment is lost)',
        additional_constraints='one of ' + ', '.join(INPUT_QOS_CHOICES))


def input_qos_profile(choice: str, depth: int = 2) -> QoSProfile:
    """
    Return the subscription QoS of an ``input_qos`` value.

    :raises ValueError: ``choice`` is not one of :data:`INPUT_QOS_CHOICES`.
    """
    if choice not in INPUT_QOS_CHOICES:
        raise ValueError(f'input_qos must be one of {", ".join(INPUT_QOS_CHOICES)}, '
                         f'got {choice!r}')
    if choice == 'sensor_data':
        return qos_profile_sensor_data
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def choice_parameter_reason(params: Iterable[Parameter],
                            choices: Mapping[str, Sequence[str]]) -> Optional[str]:
    """
    Why a parameter update must be refused because a value is not one of its allowed choices.

    :param choices: parameter name -> its allowed values (string parameters a descriptor's range
        cannot constrain); parameters not named here are not checked.
    :returns: the reason for the first parameter whose value is not allowed; None when all are.
    """
    for p in params:
        allowed = choices.get(p.name)
        if allowed is not None and p.value not in allowed:
            return f'{p.name} must be one of {", ".join(allowed)}, got {p.value!r}'
    return None


def nonfinite_parameter_reason(params: Iterable[Parameter]) -> Optional[str]:
    """
    Why a parameter update with a NaN or infinite double must be refused.

    Why a parameter update must be refused because a double (or an element of a double
    array) is NaN or infinite; None when every value is finite.

    A ranged double already refuses NaN (rclpy's range test), but an unranged double, every
    double array and a value given where no descriptor applies do not.
    """
    for p in params:
        if p.type_ == Parameter.Type.DOUBLE:
            values = [p.value]
        elif p.type_ == Parameter.Type.DOUBLE_ARRAY:
            values = list(p.value)
        else:
            continue
        bad = [v for v in values if not math.isfinite(v)]
        if bad:
            return f'parameter {p.name} must be finite, got {p.value}'
    return None


def reject_nonfinite_parameters(node: Any) -> None:
    """
    Add an on-set-parameters callback to ``node`` that refuses NaN/inf doubles.

    Call it in the node's ``__init__`` before declaring parameters, so start-up overrides
    (``-p name:=.nan``) are checked too (the declaration then raises, which
    :func:`stereo_manip_tools.robustness.create_node_or_exit` turns into one line + exit 1).
    """
    def check(params: Iterable[Parameter]) -> SetParametersResult:
        reason = nonfinite_parameter_reason(params)
        return SetParametersResult(successful=reason is None, reason=reason or '')
    node.add_on_set_parameters_callback(check)
