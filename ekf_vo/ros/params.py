"""ROS parameters from the typed config dataclasses of :mod:`ekf_vo.config`.

One source of truth: every field of a config dataclass (``VoConfig``, ``NodeConfig``,
``MapNodeConfig``) becomes one ROS parameter with the same name, default, description
(:func:`ekf_vo.config.describe`: meaning, unit, range) and range in its
``ParameterDescriptor``, so ``ros2 param describe`` shows what the YAML documents.

Mapping of field defaults to ROS parameter types:

====================  ==========================================================
default               ROS parameter
====================  ==========================================================
``bool``              bool
``int``               integer, ``integer_range`` from metadata ``lo``/``hi``
``float``             double, ``floating_point_range`` from metadata ``lo``/``hi``
``str``               string; ``choices`` listed in ``additional_constraints``
``tuple``/``list``    double array (string array when every element is a str);
                      read back as a tuple
====================  ==========================================================

ROS types are strict (as in rclcpp): ``-p publish_rate_hz:=5`` is an integer and is
rejected for a double parameter; write ``5.0``. Range and choice checks happen twice: rclpy
applies the descriptor ranges, and the dataclass ``validate()`` (which may check more, e.g.
a unit quaternion) runs on declaration and, through :func:`install_validation`, on every
``set_parameters``.

Several dataclasses can share one node (vo_node declares ``VoConfig`` and ``NodeConfig``):
each field name must belong to exactly one of them, and each validation callback only looks
at its own fields.
"""
from __future__ import annotations

import dataclasses
import logging
from typing import Any, Callable, TypeVar

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.exceptions import (InvalidParameterTypeException, InvalidParameterValueException,
                              ParameterAlreadyDeclaredException)
from rclpy.node import Node
from rclpy.parameter import Parameter

from ekf_vo.config import ConfigError, describe, validate_dataclass

logger = logging.getLogger(__name__)

__all__ = ['declare_from_dataclass', 'install_validation', 'descriptor_for', 'ros_default',
           'build_config', 'ValidationHandle']

T = TypeVar('T')

_INT64_MIN, _INT64_MAX = -2**63, 2**63 - 1
_DOUBLE_MAX = 1.7976931348623157e308


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    raise ConfigError(f'config field {f.name} has no default; cannot declare it as a parameter')


def _is_str_sequence(value: Any) -> bool:
    return len(value) > 0 and all(isinstance(v, str) for v in value)


def ros_default(f: dataclasses.Field) -> Any:
    """The value handed to ``declare_parameter`` for field ``f`` (tuples become lists).

    An empty sequence default is declared as ``Parameter.Type.DOUBLE_ARRAY`` (rclpy cannot
    infer a type from ``[]``).
    """
    default = _default(f)
    if isinstance(default, (tuple, list)):
        if not default:
            return Parameter.Type.DOUBLE_ARRAY
        if _is_str_sequence(default):
            return [str(v) for v in default]
        return [float(v) for v in default]
    return default


def descriptor_for(f: dataclasses.Field) -> ParameterDescriptor:
    """ParameterDescriptor of field ``f``: description, range, choices."""
    meta = f.metadata
    default = _default(f)
    desc = ParameterDescriptor(description=describe(f) if 'doc' in meta else f.name,
                               read_only=bool(meta.get('read_only', False)))
    lo, hi = meta.get('lo'), meta.get('hi')
    if isinstance(default, bool):
        pass
    elif isinstance(default, int) and (lo is not None or hi is not None):
        desc.integer_range = [IntegerRange(
            from_value=int(lo) if lo is not None else _INT64_MIN,
            to_value=int(hi) if hi is not None else _INT64_MAX, step=0)]
    elif isinstance(default, float) and (lo is not None or hi is not None):
        desc.floating_point_range = [FloatingPointRange(
            from_value=float(lo) if lo is not None else -_DOUBLE_MAX,
            to_value=float(hi) if hi is not None else _DOUBLE_MAX, step=0.0)]
    if meta.get('choices'):
        desc.additional_constraints = 'one of: ' + ', '.join(str(c) for c in meta['choices'])
    if meta.get('unit') and isinstance(default, (tuple, list)):
        desc.additional_constraints = (desc.additional_constraints + '; ' if
                                       desc.additional_constraints else '') + \
            f'{len(default)} values, unit {meta["unit"]}'
    return desc


def _from_ros(f: dataclasses.Field, value: Any) -> Any:
    """A ROS parameter value -> the Python type of the field (arrays -> tuple)."""
    default = _default(f)
    if isinstance(default, (tuple, list)):
        if value is None:
            return type(default)()
        seq = list(value)
        if default and _is_str_sequence(default):
            return type(default)(str(v) for v in seq)
        try:
            return type(default)(float(v) for v in seq)
        except (TypeError, ValueError):
            raise ConfigError(f'{f.name} must be a list of numbers, got {value!r}') from None
    return value


def build_config(cls: type[T], values: dict[str, Any]) -> T:
    """Instantiate ``cls`` from ``values`` and validate it (its ``validate()`` if present).

    Raises:
        ConfigError: a value is of the wrong type, out of range or inconsistent.
    """
    try:
        inst = cls(**values)
    except TypeError as exc:
        raise ConfigError(f'{cls.__name__}: {exc}') from None
    validate = getattr(inst, 'validate', None)
    try:
        if callable(validate):
            validate()
        else:
            validate_dataclass(inst)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f'{cls.__name__}: {exc}') from None
    return inst


def declare_from_dataclass(node: Node, cls: type[T]) -> T:
    """Declare one ROS parameter per field of the dataclass ``cls``; return the validated config.

    Overrides (``--ros-args -p``, ``--params-file``) take precedence over the defaults, as
    for any declared parameter.

    Raises:
        ConfigError: an override has the wrong type or is out of range, a field name is
            already declared on ``node`` (by another class), or the assembled config fails
            ``validate()``. The message names the node and the parameter.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f'{cls!r} is not a dataclass')
    name = node.get_name()
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        try:
            p = node.declare_parameter(f.name, ros_default(f), descriptor_for(f))
        except ParameterAlreadyDeclaredException:
            raise ConfigError(
                f'{name}: parameter {f.name} of {cls.__name__} is already declared '
                '(a parameter name may belong to only one config class)') from None
        except InvalidParameterTypeException as exc:
            raise ConfigError(
                f'{name}: parameter {f.name} has the wrong type ({exc}); expected '
                f'{type(_default(f)).__name__} like the default {_default(f)!r} '
                '(doubles need a decimal point: 5.0, not 5)') from None
        except InvalidParameterValueException as exc:
            raise ConfigError(f'{name}: invalid value for parameter {f.name}: {exc} '
                              f'[{describe(f)}]') from None
        values[f.name] = _from_ros(f, p.value)
    try:
        return build_config(cls, values)
    except ConfigError as exc:
        raise ConfigError(f'{name}: {exc}') from None


class ValidationHandle:
    """What :func:`install_validation` registered; ``remove()`` unregisters both callbacks."""

    def __init__(self, node: Node, on_set: Callable, post_set: Callable) -> None:
        self._node = node
        self.on_set = on_set
        self.post_set = post_set

    def remove(self) -> None:
        self._node.remove_on_set_parameters_callback(self.on_set)
        self._node.remove_post_set_parameters_callback(self.post_set)


def install_validation(node: Node, cls: type[T], on_change: Callable[[T], None]
                       ) -> ValidationHandle:
    """Validate every change of ``cls``'s parameters on ``node``; report accepted ones.

    Registers an ``add_on_set_parameters_callback`` that builds ``cls`` from the current
    values merged with the proposed ones and rejects the whole (atomic) change with
    ``SetParametersResult(successful=False, reason=...)`` if it does not validate.
    Parameters that are not fields of ``cls`` are ignored (accepted), so several classes
    can validate on one node. After a change was applied, a post-set callback calls
    ``on_change(new_config)`` (only when all of ``cls``'s parameters are declared; so not
    during :func:`declare_from_dataclass`). An exception in ``on_change`` is logged, not
    raised.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}

    def current_values() -> dict[str, Any]:
        values = {}
        for pname, f in fields.items():
            if node.has_parameter(pname):
                values[pname] = _from_ros(f, node.get_parameter(pname).value)
            else:
                values[pname] = _default(f)
        return values

    def on_set(params: list[Parameter]) -> SetParametersResult:
        mine = [p for p in params if p.name in fields]
        if not mine:
            return SetParametersResult(successful=True)
        try:
            values = current_values()
            for p in mine:
                if p.type_ == Parameter.Type.NOT_SET:
                    return SetParametersResult(
                        successful=False, reason=f'parameter {p.name} cannot be unset')
                values[p.name] = _from_ros(fields[p.name], p.value)
            build_config(cls, values)
        except ConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def post_set(params: list[Parameter]) -> None:
        if not any(p.name in fields for p in params):
            return
        if not all(node.has_parameter(n) for n in fields):
            return  # still declaring
        try:
            inst = build_config(cls, current_values())
            on_change(inst)
        except Exception as exc:  # noqa: BLE001 - never break the parameter service
            node.get_logger().error(f'applying new {cls.__name__} failed: {exc!r}')

    node.add_on_set_parameters_callback(on_set)
    node.add_post_set_parameters_callback(post_set)
    return ValidationHandle(node, on_set, post_set)


#: parameters every rclpy node accepts without declaring them
_ROS_BUILTIN_PARAMETERS = frozenset({'use_sim_time', 'start_type_description_service'})


def unknown_parameters(node: Node) -> list[tuple[str, str | None]]:
    """Parameters given to `node` (params file, `-p`) that no ekf_vo node declares, each
    with the closest known name (or None). Names of every ekf_vo config count as known, so
    `ekf_vo_nodes` (both nodes in one process, one set of overrides) warns only on names
    neither node knows."""
    import difflib

    from ekf_vo.config import MapNodeConfig, NodeConfig, VoConfig
    known = {f.name for cls in (VoConfig, NodeConfig, MapNodeConfig)
             for f in dataclasses.fields(cls)}
    known |= _ROS_BUILTIN_PARAMETERS | set(node._parameters)
    given = set(getattr(node, '_parameter_overrides', {}))   # rclpy keeps them here
    return [(name, next(iter(difflib.get_close_matches(name, sorted(known), n=1)), None))
            for name in sorted(given - known)]


def warn_unknown_parameters(node: Node) -> int:
    """Log one warning per unknown parameter (see unknown_parameters); returns how many."""
    unknown = unknown_parameters(node)
    for name, closest in unknown:
        hint = f"; did you mean '{closest}'?" if closest else ''
        node.get_logger().warning(f"unknown parameter '{name}' ignored{hint}")
    return len(unknown)
