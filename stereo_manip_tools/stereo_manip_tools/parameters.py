"""ParameterDescriptor builders shared by every node (no rclpy needed, only rcl_interfaces).

Every node declares each parameter with a description, a range and read-only where it must be;
these helpers keep those declarations short and identical across packages.
"""

from __future__ import annotations

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, \
    ParameterType

__all__ = ['float_descriptor', 'int_descriptor', 'string_descriptor', 'bool_descriptor']


def float_descriptor(description: str, low: float, high: float,
                     read_only: bool = False) -> ParameterDescriptor:
    """A double parameter in ``[low, high]``."""
    return ParameterDescriptor(type=ParameterType.PARAMETER_DOUBLE, description=description,
                               read_only=read_only,
                               floating_point_range=[FloatingPointRange(
                                   from_value=float(low), to_value=float(high))])


def int_descriptor(description: str, low: int, high: int,
                   read_only: bool = False) -> ParameterDescriptor:
    """An integer parameter in ``[low, high]`` (step 1)."""
    return ParameterDescriptor(type=ParameterType.PARAMETER_INTEGER, description=description,
                               read_only=read_only,
                               integer_range=[IntegerRange(from_value=int(low),
                                                           to_value=int(high), step=1)])


def string_descriptor(description: str, read_only: bool = False) -> ParameterDescriptor:
    """A string parameter (validate its value in the node's on-set callback)."""
    return ParameterDescriptor(type=ParameterType.PARAMETER_STRING, description=description,
                               read_only=read_only)


def bool_descriptor(description: str, read_only: bool = False) -> ParameterDescriptor:
    """A boolean parameter."""
    return ParameterDescriptor(type=ParameterType.PARAMETER_BOOL, description=description,
                               read_only=read_only)
