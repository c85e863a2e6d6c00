"""An env's card: what the library knows of an env beyond its equations, a value that
its case module declares beside its physics and that registering an id attaches to it
(a variant takes its base's card, or one made from it with ``dataclasses.replace``).
Benchmarks, reports and the test suite read it; nothing keeps a list of envs of its
own. Facts an env does not have stay None: a user's env registers without them."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple


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
    :data:`SOURCES`) and ``where`` it is read or computed. Where the score is a quantity
    measured from an ``origin`` (a reward ``nu_ref - Nu`` summed: the origin is the score
    of Nu = 0), the ratio scales the quantity, not the score."""

    source: str
    where: str
    score: float | None = None
    ratio: float | None = None
    origin: float = 0.0

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"a reference's source must be one of {', '.join(SOURCES)}, got {self.source!r}")
        if (self.score is None) == (self.ratio is None):
            raise ValueError("a reference is a score or a ratio to no control's score, one of the two")

    def value(self, uncontrolled: float) -> float:
        """The reference score beside no control scoring ``uncontrolled``."""
        if self.score is not None:
            return self.score
        return self.origin + self.ratio * (uncontrolled - self.origin)

    def label(self) -> str:
        """How a table shows it: the number and its source."""
        number = f"{self.score:g}" if self.score is not None else f"{self.ratio:.4g} x no control"
        if self.score is None and self.origin:
            number = f"{self.origin:g} - {self.ratio:.4g} x ({self.origin:g} - no control)"
        return f"{number} ({self.source})"


class FrameInputs(NamedTuple):
    """What a frame is drawn from: the member ``member`` of an env of ``physics`` and
    ``params`` (per-member values: its own are entries ``member``), its ``states`` to
    draw, on the CPU, without the batch dimension (the episode so far when ``recorded``,
    else the current one), and ``step``, its actions since its reset (the clock of the
    last state)."""

    physics: Any
    params: Any
    member: int
    states: list
    step: int
    recorded: bool


@dataclasses.dataclass(frozen=True)
class Card:
    """What the library knows of an env beyond its equations (every field optional)."""

    # what the env solves: "ode", "1-D" or "2-D" (a flow in one or two space dimensions)
    family: str | None = None
    # whether an action costs seconds rather than milliseconds: tests and benchmarks
    # run fewer of its steps
    costly: bool = False
    # transitions per second of the published single-env NumPy/Numba code on one core
    # of this project's Intel Xeon machine kind (None: no published code is run here)
    published_speed: float | None = None
    # the speed-up over it aimed at, at the best batch size, float32, 2 CPU cores
    speed_target: float | None = None
    # the score the paper's PPO reaches, read from its curves as the mean of the last
    # tenth of its training episodes: the "= 1" of the reports' normalised scores
    # where the env declares no other ``reference``
    paper_ppo: float | None = None
    # the "= 1" of an env that has no paper's PPO, with its source (None, and no
    # ``paper_ppo``: the protocol has nothing to normalise by)
    reference: Reference | None = None
    # the gradient check on the published settings (None where the actions are discrete)
    gradcheck: GradCheck | None = None
    # parameters that make an episode cheap, for the behaviour tests run on every env
    test_settings: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    # the frame ``render()`` draws, ``frame(FrameInputs) -> H x W x 3 uint8 array``
    # (None: the env draws nothing)
    frame: Callable[[FrameInputs], Any] | None = None

    def scale_reference(self) -> Reference | None:
        """The "= 1" of this env's normalised scores: its ``reference``, or its paper's
        PPO score, or None."""
        if self.reference is not None:
            return self.reference
        if self.paper_ppo is not None:
            return Reference(PAPER_PPO, "read from the paper's learning curves", score=self.paper_ppo)
        return None
