"""What the offline runner is told: its parameters (the params YAML, ``--set``) and the
camera's extrinsic, read the way vo_node reads them (one source: ekf_vo/config.py)."""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..config import (ConfigError, NodeConfig, VoConfig, load_yaml_params, parse_value,
                      split_params)


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``['name=value', ...]`` -> ``{name: typed value}`` for :class:`VoConfig` fields.

    The type is the field's default type (bool, int, float, str; a tuple takes
    comma-separated numbers).

    Raises:
        ConfigError: malformed item, unknown parameter or a value of the wrong type.
    """
    core = {f.name: f for f in dataclasses.fields(VoConfig)}
    node = {f.name for f in dataclasses.fields(NodeConfig)}
    out: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition('=')
        name = name.strip()
        if not sep or not name:
            raise ConfigError(f'--set expects name=value, got {item!r}')
        if name not in core:
            if name in node:
                raise ConfigError(f'--set {name}: a vo_node ROS parameter, not used by the '
                                  f'offline runner (core parameters only)')
            raise ConfigError(f'--set {name}: unknown parameter (list them with '
                              f'ekf-vo-params)')
        out[name] = parse_value(name, text, core[name].default, '--set ')
    return out


def make_config(params: str | Path | Mapping[str, Any] | VoConfig | None = None,
                overrides: Mapping[str, Any] | None = None) -> VoConfig:
    """The core config from a params YAML path, a flat vo_node parameter mapping, a
    VoConfig or None (defaults), with ``overrides`` (core field -> value) applied.

    Raises:
        ConfigError: unknown parameter, wrong type or out-of-range value.
    """
    if params is None:
        cfg = VoConfig()
    elif isinstance(params, VoConfig):
        cfg = params
    else:
        if isinstance(params, (str, Path)):
            if not Path(params).is_file():
                raise ConfigError(f'params file not found: {params}')
            values = load_yaml_params(str(params), 'vo_node')
        else:
            values = dict(params)
        cfg, _node = split_params(values)
    if overrides:
        names = {f.name for f in dataclasses.fields(VoConfig)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise ConfigError(f'unknown core parameter(s): {unknown}')
        cfg = VoConfig.from_mapping({**dataclasses.asdict(cfg), **dict(overrides)})
    return cfg.validate()


def base_extrinsic(params: str | Path | Mapping[str, Any] | VoConfig | None
                   ) -> np.ndarray:
    """T_base_cam (4x4) from vo_node's T_base_cam_xyz / _xyzw in the params YAML or
    mapping (their defaults otherwise): the metric scale's gravity and lever arm."""
    from ..core.frames import optical_to_body_extrinsic
    node = NodeConfig()
    if isinstance(params, (str, Path)):
        node = split_params(load_yaml_params(str(params), 'vo_node'))[1]
    elif isinstance(params, Mapping):
        node = split_params(dict(params))[1]
    return optical_to_body_extrinsic(node.T_base_cam_xyz, node.T_base_cam_xyzw)
