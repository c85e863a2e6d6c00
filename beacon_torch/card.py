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


# where a normalised score's "= 1" comes from
PAPER_PPO = "the paper's PPO"
PUBLISHED_RESULT = "a published result"
PHYSICAL_LIMIT = "the physical limit"
COMPUTED = "a computed reference"
SOURCES = (PAPER_PPO, PUBLISHED_RESULT, PHYSICAL_LIMIT, COMPUTED)


@dataclasses.dataclass(frozen=True)
class Reference:
    """The "= 1" of an env's normalised scores (their "0" is no control from the same
    starts): an episode's ``score``, or a ``ratio`` to no control's score from the same
    starts (a published reduction measured on another grid, whose absolute level differs
    from this one's, carries over as a share), with its ``source`` (one of
    :data:`SOURCES`) and ``where`` it is read or computed."""

    source: str
    where: str
    score: float | None = None
    ratio: float | None = None

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"a reference's source must be one of {', '.join(SOURCES)}, got {self.source!r}")
        if (self.score is None) == (self.ratio is None):
            raise ValueError("a reference is a score or a ratio to no control's score, one of the two")

    def value(self, uncontrolled: float) -> float:
        """The reference score beside no control scoring ``uncontrolled``."""
        return self.score if self.score is not None else self.ratio * uncontrolled

    def label(self) -> str:
        """How a table shows it: the number and its source."""
        number = f"{self.score:g}" if self.score is not None else f"{self.ratio:.4g} x no control"
        return f"{number} ({self.source})"


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
    # tenth of its training episodes: the "= 1" of the reports' normalised scores
    # where the env declares no other ``reference``
    paper_ppo: ClassVar[float | None] = None
    # the "= 1" of an env that has no paper's PPO, with its source (None, and no
    # ``paper_ppo``: the protocol has nothing to normalise by)
    reference: ClassVar[Reference | None] = None
    # the gradient check on the published settings (None where the actions are discrete)
    gradcheck: ClassVar[GradCheck | None] = None
    # parameters that make an episode cheap, for the behaviour tests run on every env
    test_settings: ClassVar[dict[str, Any]] = {}

    @classmethod
    def scale_reference(cls) -> Reference | None:
        """The "= 1" of this env's normalised scores: its ``reference``, or its paper's
        PPO score, or None."""
        if cls.reference is not None:
            return cls.reference
        if cls.paper_ppo is not None:
            return Reference(PAPER_PPO, "read from the paper's learning curves", score=cls.paper_ppo)
        return None

    @classmethod
    def base_id(cls) -> str:
        """The benchmark env this one is a variant of, or its own id: a variant
        subclasses its base env, against whose scores and speed it is measured."""
        for klass in cls.__mro__[1:]:
            if klass.__dict__.get("env_id"):
                return klass.env_id
        return cls.env_id
