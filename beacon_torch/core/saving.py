"""An env's state saved and restored: where every member is, the generators and the
parameters, as a state dict that ``load_state_dict`` continues from."""

from __future__ import annotations

import dataclasses

import torch


class Saving:
    """``state_dict`` and ``load_state_dict`` of :class:`~beacon_torch.base.FlowEnv`
    (a part of it)."""

    def state_dict(self, *args, destination=None, prefix: str = "", keep_vars: bool = False):
        """Where the env is: the state of every member (``state.<key>``), the actions
        taken in their episodes (``count``), the generators' states (``rng``,
        ``action_rng``) and the parameters it steps with (``params``);
        :meth:`load_state_dict` continues from there (an env of the same id, batch size
        and parameters)."""
        out = super().state_dict(*args, destination=destination, prefix=prefix, keep_vars=keep_vars)
        if self._state is not None:
            for key, value in self._state._asdict().items():
                out[f"{prefix}state.{key}"] = value if keep_vars else value.detach()
            out[f"{prefix}count"] = self._count.clone()
        out[f"{prefix}rng"] = self.rng.get_state()
        out[f"{prefix}action_rng"] = self.action_rng.get_state()
        out[f"{prefix}params"] = {
            f.name: getattr(self.params, f.name).detach().clone()
            if isinstance(getattr(self.params, f.name), torch.Tensor)
            else getattr(self.params, f.name)
            for f in dataclasses.fields(self.params)
        }
        return out

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Continue from :meth:`state_dict` (its state checked as :meth:`set_state`
        checks it, after the cast to this env's dtype). The parameters it records must
        be this env's (a state of other physics is refused); ``strict`` (the default)
        also requires every entry a stepped env's state dict has, and no other."""
        name = self.env_id or type(self).__name__
        if not isinstance(state_dict, dict):
            raise TypeError(f"{name}: a state dict is a dict (env.state_dict()), got {type(state_dict).__name__}")
        state = {key.removeprefix("state."): value for key, value in state_dict.items() if key.startswith("state.")}
        entries = ("count", "rng", "action_rng", "params")
        unknown = set(state_dict) - {f"state.{k}" for k in state} - set(entries)
        missing = [] if state else [f"state.{k}" for k in self.physics.state_type._fields]
        missing += [key for key in entries if key not in state_dict and (key != "count" or state)]
        if strict and (unknown or missing):
            raise KeyError(
                f"{name}: the state dict has unknown entries {sorted(unknown)} and lacks {missing}; "
                f"load_state_dict(..., strict=False) loads what it holds"
            )
        if "params" in state_dict:
            self._check_same_params(state_dict["params"])
        generators = {key: getattr(self, key) for key in ("rng", "action_rng") if key in state_dict}
        for key, generator in generators.items():
            saved, own = state_dict[key], generator.get_state()
            if not isinstance(saved, torch.Tensor) or saved.dtype != torch.uint8 or saved.shape != own.shape:
                raise ValueError(
                    f"{name}: {key!r} must be a generator state of this device (a uint8 tensor "
                    f"of shape {tuple(own.shape)})"
                )
        if state:
            self.set_state(state, state_dict.get("count", 0))
        for key, generator in generators.items():
            generator.set_state(state_dict[key])
        return torch.nn.modules.module._IncompatibleKeys([], [])

    def _check_same_params(self, saved) -> None:
        """Refuse the parameters of a saved state dict that are not this env's."""
        name = self.env_id or type(self).__name__
        own = {f.name: getattr(self.params, f.name) for f in dataclasses.fields(self.params)}
        if not isinstance(saved, dict) or set(saved) != set(own):
            raise ValueError(f"{name}: the state dict's 'params' are not those of {name} ({sorted(own)})")
        for key, mine in own.items():
            theirs = saved[key]
            if isinstance(mine, torch.Tensor):
                same = (
                    isinstance(theirs, (torch.Tensor, int, float))
                    and not isinstance(theirs, bool)
                    and torch.as_tensor(theirs).numel() in (1, mine.numel())
                    and bool((torch.as_tensor(theirs).to(mine.device, mine.dtype) == mine.detach()).all())
                )
            else:
                same = type(theirs) is type(mine) and theirs == mine
            if not same:
                shown = theirs.tolist() if isinstance(theirs, torch.Tensor) and theirs.numel() < 8 else theirs
                raise ValueError(
                    f"{name}: the state dict was saved by an env with other parameters ({key} = {shown!r} there, "
                    f"{mine.tolist() if isinstance(mine, torch.Tensor) else mine!r} here); make the env with its "
                    f"parameters to continue it"
                )
