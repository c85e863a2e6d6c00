"""An env's card: what the library knows of an env beyond its equations, declared as
class attributes in its module (a variant subclasses its base env and inherits it).
Benchmarks, reports and the test suite read it; nothing keeps a list of envs of its
own. Facts an env does not have stay None: a user's env registers without them."""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar


@dataclasses.dataclass(frozen=True)
class GradCheck:
    """An env's gradient check (``beacon_torch.gradcheck``): the reward summed over
    ``steps`` random actions after ``warmup`` of them, differentiated with respect to
    the actions and to the parameter ``param`` at ``value``, with the other parameters
    ``params``."""

    param: str
    value: float
    warmup: int
    steps: int
    params: dict[str, Any] = dataclasses.field(default_factory=dict)


class Card:
    """The card's fields, with what an env that says nothing has."""

    env_id: ClassVar[str] = ""
    # what the env solves: "ode", "1-D" or "2-D" (a flow in one or two space dimensions)
    family: ClassVar[str]
    # whether an action costs seconds rather than milliseconds: tests and benchmarks
    # run fewer of its steps
    costly: ClassVar[bool] = False
    # transitions per second of the published single-env NumPy/Numba code on one core
    # of this project's Intel Xeon machine kind (None: no published code is run here)
    published_speed: ClassVar[float | None] = None
    # the speed-up over it aimed at, at the best batch size, float32, 2 CPU cores
    speed_target: ClassVar[float | None] = None
    # the score the paper's PPO reaches, read from its curves as the mean of the last
    # tenth of its training episodes (the 1 of the reports' normalised scores; None:
    # no paper score, and the protocol has nothing to normalise by)
    paper_ppo: ClassVar[float | None] = None
    # the gradient check on the published settings (None where the actions are discrete)
    gradcheck: ClassVar[GradCheck | None] = None
    # parameters that make an episode cheap, for the behaviour tests run on every env
    test_settings: ClassVar[dict[str, Any]] = {}

    @classmethod
    def base_id(cls) -> str:
        """The benchmark env this one is a variant of, or its own id: a variant
        subclasses its base env, against whose scores and speed it is measured."""
        for klass in cls.__mro__[1:]:
            if klass.__dict__.get("env_id"):
                return klass.env_id
        return cls.env_id
