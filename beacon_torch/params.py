"""Physical parameters of an environment: declaration and validation.

Each env declares a frozen dataclass whose fields are made with :func:`param`; the field
metadata says which values are admissible. :func:`resolve_params` turns the user's
keyword arguments into an instance of that dataclass, rejecting unknown names, wrong
types, non-finite and out-of-range values with an error that names the parameter.

A value is either a scalar, shared by the whole batch, or one value per batch member
(a 1-D sequence, array or tensor of the batch's length). Inside the env, a parameter that
may differ per member is always a ``[batch]`` tensor on the env's device and dtype (a
scalar is repeated), so that the physics has one code path; parameters that fix the
grid, the actuators or a cached start (``per_member=False``) stay Python numbers.

A real parameter may also be a tensor that requires grad (a number or one value per
member), for environments made with ``differentiable=True``: it is kept as given (cast
to the env's dtype and device), so that gradients of the rewards reach it. Parameters
that fix the grid or the number of actuators cannot be differentiated; the few shared
ones that only enter the equations (``differentiable=True`` in :func:`param`) may.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import re
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

_KINDS = ("real", "int", "complex", "choice")


def param(
    default: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    kind: str = "real",
    per_member: bool = True,
    differentiable: bool | None = None,
    choices: tuple[str, ...] = (),
    doc: str = "",
) -> Any:
    """Declare one parameter of an env's ``Params`` dataclass.

    ``low``/``high`` bound the value (the modulus, for complex parameters); ``*_open``
    excludes the bound itself. ``per_member=False`` forbids a per-member sequence, for
    parameters that fix the grid or the number of actuators. ``differentiable`` says
    whether a tensor requiring grad is accepted; by default, for real parameters that
    may vary per member. ``kind="choice"`` declares a word out of ``choices`` (one for
    the whole batch; a default of None lets the dataclass decide).
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
    if kind == "choice":
        per_member = False
    meta = dict(
        low=low,
        high=high,
        low_open=low_open,
        high_open=high_open,
        kind=kind,
        per_member=per_member,
        differentiable=(kind == "real" and per_member) if differentiable is None else differentiable,
        choices=tuple(choices),
        doc=doc,
        # a word whose default is None takes None (the dataclass decides); no other
        nullable=default is None,
    )
    return dataclasses.field(default=default, metadata=meta)


def number(value: Any) -> float:
    """A shared parameter as a Python number (for cache keys, grid sizes and step
    counts), whether it was given as a number or as a tensor that requires grad."""
    return float(value.detach()) if isinstance(value, torch.Tensor) else value


def describe(params_cls: type) -> list[dict[str, Any]]:
    """Name, default, admissible range and description of each parameter (for docs/CLI)."""
    rows = []
    for f in dataclasses.fields(params_cls):
        m = f.metadata
        rows.append(dict(name=f.name, default=f.default, range=_range_text(m), doc=m["doc"]))
    return rows


def markdown(params_cls: type) -> str:
    """The parameters of an env as the Markdown table of its page (docs/envs), written
    from their declarations, so that the page cannot drift from the code."""
    rows = ["| name | default | admissible | meaning |", "|---|---|---|---|"]
    for f in dataclasses.fields(params_cls):
        m = f.metadata
        admissible = ", ".join(f'`"{c}"`' for c in m["choices"]) if m["kind"] == "choice" else _range_text(m)
        if m["kind"] == "int" and m["low"] is not None and m["high"] is not None:
            admissible = f"{m['low']}..{m['high']}"
        if not m["per_member"]:
            admissible += ", one value"
        rows.append(
            f"| `{f.name}` | {_default_text(f.default)} | {admissible.replace('|', chr(92) + '|')} | {m['doc']} |"
        )
    return "\n".join(rows)


def _default_text(value: Any) -> str:
    if isinstance(value, str):
        return f'`"{value}"`'
    if isinstance(value, complex):
        return f"{_short(value.real)} {'-' if value.imag < 0 else '+'} {_short(abs(value.imag))}i"
    if isinstance(value, float):
        return _short(value)
    return f"`{value}`" if value is None else str(value)


def _short(x: float) -> str:
    """A number as people write it: 1e6 rather than 1e+06."""
    return f"{x:g}".replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")


def _range_text(m) -> str:
    if m["kind"] == "choice":
        return "one of " + ", ".join(repr(c) for c in m["choices"])
    lo = "-inf" if m["low"] is None else _short(m["low"])
    hi = "inf" if m["high"] is None else _short(m["high"])
    left = "(" if (m["low_open"] or m["low"] is None) else "["
    right = ")" if (m["high_open"] or m["high"] is None) else "]"
    text = f"{left}{lo}, {hi}{right}"
    return f"|value| in {text}" if m["kind"] == "complex" else text


def _check_scalar(name: str, value: Any, m, where: str = "") -> complex | float | int:
    kind = m["kind"]
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"parameter {name!r}{where} must be a {kind} number, got a bool")
    if kind == "complex":
        if not isinstance(value, numbers.Complex):
            raise TypeError(f"parameter {name!r}{where} must be a complex number, got {type(value).__name__}")
        value = complex(value)
        finite = math.isfinite(value.real) and math.isfinite(value.imag)
        size = abs(value)
    elif kind == "int":
        if not isinstance(value, numbers.Integral):
            if isinstance(value, numbers.Real) and float(value).is_integer():
                value = int(value)
            else:
                raise TypeError(f"parameter {name!r}{where} must be an integer, got {value!r}")
        value = int(value)
        finite, size = True, value
    else:
        if not isinstance(value, numbers.Real):
            raise TypeError(f"parameter {name!r}{where} must be a real number, got {type(value).__name__}")
        value = float(value)
        finite, size = math.isfinite(value), value
    if not finite:
        raise ValueError(f"parameter {name!r}{where} must be finite, got {value!r}")
    low, high = m["low"], m["high"]
    too_low = low is not None and (size <= low if m["low_open"] else size < low)
    too_high = high is not None and (size >= high if m["high_open"] else size > high)
    if too_low or too_high:
        raise ValueError(f"parameter {name!r}{where} must be in {_range_text(m)}, got {value!r}")
    return value


def _check_differentiable(name: str, value: torch.Tensor, m, n: int, device, dtype) -> torch.Tensor:
    """A parameter tensor that requires grad: its values are checked like any others,
    and the tensor itself (not a copy of its values) is what the physics uses."""
    if not m["differentiable"]:
        raise TypeError(
            f"parameter {name!r} cannot be differentiated (it fixes the grid, the actuators or "
            f"a cached start); pass a number"
        )
    if not value.is_floating_point():
        raise TypeError(f"parameter {name!r} requires grad, so it must be a floating tensor, got {value.dtype}")
    if value.ndim == 0:
        given = _check_scalar(name, value.item(), m)
        value = _still_admissible(name, value.to(device=device, dtype=dtype), [given], m)
        # per-member parameters are tensors of the batch's length wherever they are tensors
        return value.expand(n) if m["per_member"] else value
    if not m["per_member"]:
        raise TypeError(f"parameter {name!r} must be one number for the whole batch, got a sequence")
    if value.shape != (n,):
        raise ValueError(
            f"parameter {name!r} must be a number or one value per batch member "
            f"(shape ({n},)), got shape {tuple(value.shape)}"
        )
    given = [_check_scalar(name, v, m, f"[{i}]") for i, v in enumerate(value.detach().cpu().tolist())]
    return _still_admissible(name, value.to(device=device, dtype=dtype), given, m)


def _check_choice(name: str, value: Any, m) -> str | None:
    if (value is None and m.get("nullable", False)) or (isinstance(value, str) and value in m["choices"]):
        return value
    raise ValueError(f"parameter {name!r} must be {_range_text(m)}, got {value!r}")


def _check_value(name: str, value: Any, m, n: int, device, dtype) -> Any:
    if m["kind"] == "choice":
        return _check_choice(name, value, m)
    if isinstance(value, torch.Tensor) and value.requires_grad:
        return _check_differentiable(name, value, m, n, device, dtype)
    if isinstance(value, torch.Tensor) and value.ndim == 0:
        value = value.item()
    elif isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    if isinstance(value, (str, bytes)):
        raise TypeError(f"parameter {name!r} must be a {m['kind']} number, got a string")
    if isinstance(value, (torch.Tensor, np.ndarray, list, tuple)):
        if not m["per_member"]:
            raise TypeError(f"parameter {name!r} must be one number for the whole batch, got a sequence")
        values = value.detach().cpu().tolist() if isinstance(value, torch.Tensor) else np.asarray(value).tolist()
        if np.ndim(values) != 1 or len(values) != n:
            shape = tuple(np.shape(values))
            raise ValueError(
                f"parameter {name!r} must be a number or one value per batch member (shape ({n},)), got shape {shape}"
            )
        checked = [_check_scalar(name, v, m, f"[{i}]") for i, v in enumerate(values)]
        return _member_tensor(name, checked, m, device, dtype)
    value = _check_scalar(name, value, m)
    return _member_tensor(name, [value], m, device, dtype, repeat=n) if m["per_member"] else value


def _member_tensor(name: str, values: list, m, device, dtype, repeat: int = 1) -> torch.Tensor:
    """One value per member (``values``, each repeated ``repeat`` times) as a tensor of
    the parameter's kind, whose values (after the cast to the env's precision) are still
    admissible."""
    if m["kind"] == "int":
        return torch.tensor(values, dtype=torch.int64, device=device).repeat(repeat)
    if m["kind"] == "complex":
        dtype = torch.complex128 if dtype == torch.float64 else torch.complex64
    return _still_admissible(name, torch.tensor(values, dtype=dtype, device=device), values, m).repeat(repeat)


def _still_admissible(name: str, tensor: torch.Tensor, given: list, m) -> torch.Tensor:
    """``tensor`` (``given`` cast to a precision), refused where the cast took a value
    out of the parameter's range (``re=1e-300`` is 0 in float32, ``1e39`` infinite)."""
    size = tensor.detach().abs() if tensor.is_complex() else tensor.detach()
    bad = ~torch.isfinite(size)
    if m["low"] is not None:
        bad |= size <= m["low"] if m["low_open"] else size < m["low"]
    if m["high"] is not None:
        bad |= size >= m["high"] if m["high_open"] else size > m["high"]
    if bool(bad.any()):
        i = int(bad.reshape(-1).nonzero()[0, 0])
        cast = tensor.detach().reshape(-1)[i].item()
        raise ValueError(
            f"parameter {name!r} = {given[i]!r} becomes {cast!r} in {tensor.dtype} (its range is "
            f"{_range_text(m)}); use float64 or another value"
        )
    return tensor


def resolve_params(
    params_cls: type,
    overrides: dict[str, Any],
    *,
    batch_size: int,
    device: torch.device,
    dtype: torch.dtype,
    env_id: str = "",
) -> Any:
    """Validate ``overrides`` against ``params_cls`` and return the params instance."""
    fields = {f.name: f for f in dataclasses.fields(params_cls)}
    unknown = sorted(set(overrides) - set(fields))
    if unknown:
        label = f" of {env_id}" if env_id else ""
        # Python's own words too: wrappers (TorchRL's GymEnv) retry without an option
        # the env does not take when they read them
        raise TypeError(
            f"unknown parameter {unknown[0]!r}{label} (got an unexpected keyword argument {unknown[0]!r}); "
            f"the parameters are: {', '.join(fields)}"
        )
    values = {}
    for name, f in fields.items():
        value = overrides.get(name, f.default)
        values[name] = _check_value(name, value, f.metadata, batch_size, device, dtype)
    return params_cls(**values)


def parse_value(text: str) -> Any:
    """A parameter's value as written on a command line: an integer, a real or a complex
    number, a comma-separated list of them (one per member), or else a string. A
    number written non-zero that a float rounds to zero (``1e-400``) is refused."""
    for cast in (int, float, complex):
        try:
            value = cast(text.replace(" ", ""))
        except ValueError:
            continue
        if value == 0 and re.search(r"[1-9]", re.split(r"[eE]", text)[0]):
            raise ValueError(f"{text!r} is too small for a float: it would be 0")
        return value
    if "," in text:
        return [parse_value(t) for t in text.split(",")]
    return text


def parse_assignments(items: Sequence[str], flag: str = "--param") -> dict[str, Any]:
    """``["re=80", "amp=5"]`` (the ``--param NAME=VALUE`` options of the command line and
    the recipes) as ``{"re": 80, "amp": 5}``; a name given twice is refused (which of
    the two was meant?)."""
    params = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ValueError(f"{flag} expects NAME=VALUE, got {item!r}")
        if name.strip() in params:
            raise ValueError(f"{flag} {name.strip()} is given twice; give each parameter once")
        try:
            params[name.strip()] = parse_value(value.strip())
        except ValueError as err:
            raise ValueError(f"{flag} {item}: {err}") from None
    return params


def resolved(Params: type, params: dict[str, Any], env_id: str = "") -> Any:
    """``params`` as a ``Params`` dataclass (float64, on the CPU, as many members as the
    longest per-member list), checked: what an id's sizes are computed from before any
    env is built (:meth:`beacon_torch.registry.EnvSpec.sizes`)."""
    if not isinstance(params, dict) or not all(isinstance(k, str) for k in params):
        raise TypeError(f"env parameters must be a dict of names to values, got {params!r}")
    members = max([len(v) for v in params.values() if isinstance(v, (list, tuple))], default=1)
    cpu = torch.device("cpu")
    return resolve_params(Params, params, batch_size=members, device=cpu, dtype=torch.float64, env_id=env_id)


def short_repr(params) -> str:
    """Parameters as a repr shows them: a per-member value once when the members share
    it, else its range over the members (not 64 numbers at 64 members)."""
    shown = []
    for f in dataclasses.fields(params):
        value = getattr(params, f.name)
        if isinstance(value, torch.Tensor) and value.ndim >= 1 and value.numel() > 0:
            flat = value.detach().flatten()
            if bool((flat == flat[0]).all()):
                value = repr(flat[0].item())
            elif flat.is_complex():
                value = f"<{flat.numel()} complex values>"
            else:
                value = f"<{flat.numel()} values in [{flat.min().item():.4g}, {flat.max().item():.4g}]>"
        else:
            value = repr(value)
        shown.append(f"{f.name}={value}")
    return f"{type(params).__name__}({', '.join(shown)})"
