"""The recipes' settings: one configuration object per run.

``Config`` holds what every recipe reads (the env, the run's size and its options:
seed, device, output, resume, collectors, Ray, logger, progress); each algorithm's
class adds its own fields. ``configure(PPOConfig, env_id, **overrides)`` gives a run's
settings with the per-env defaults (the paper's PPO table; the budget of the paper's
PPO for the other algorithms), checked; ``parse`` does the same from a command line,
whose ``--help`` lists every field.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from dataclasses import MISSING, dataclass, field, fields, replace
from importlib.util import find_spec
from pathlib import Path
from typing import ClassVar

import beacon_torch
from beacon_torch import threads
from beacon_torch.arguments import find_user_modules, plain
from beacon_torch.core.checks import as_device
from beacon_torch.envs.rbc2d import LEVELS as RBC2D_LEVELS
from beacon_torch.params import parse_assignments
from beacon_torch.registry import ENVS, EnvSpec, compiles_by_default, continuous_envs, env_spec
from beacon_torch.training.env import NORM_STEPS
from beacon_torch.training.evaluation import HELD_OUT, learning_curve
from beacon_torch.training.run import CHECKPOINT, MAX_HIDDEN, fits, load_checkpoint

# The per-env settings of the recipes: data of the library, read by ``configure``. Each
# table holds what differs from its class's defaults; a variant trains like its base env.
# Why each entry is what it is, with the measurements, is in docs/training.md.

# Rabault et al.'s PPO agent on the cylinder, the wakes' settings
RABAULT = dict(
    n_rollout=1600,
    frames=128_000,
    hidden=512,
    actor_lr=1e-3,
    critic_lr=1e-3,
    epochs=5,
    minibatches=5,
    gae_lambda=0.97,
)
# beyond the paper: FluidGym's runs on its RBC2D levels (Stable-Baselines3's PPO and
# its 64-wide networks: 2,048 transitions a rollout in minibatches of 64, 10 epochs,
# both rates 3e-4, GAE's lambda 0.95, gradient norm 0.5, 50,000 flow steps a run) with
# its actor, whose spread starts at 1 (with the paper's, 0.5, the easy level's three
# seeds lowered the Nusselt number of the test starts by 12.0 %, with this one by
# 16.7), its critic and its update
FLUIDGYM_PPO = dict(
    actor="free-spread",
    critic="sb3",
    update="sb3",
    frames=50_000,
    n_rollout=2048,
    minibatches=32,
    epochs=10,
    actor_lr=3e-4,
    critic_lr=3e-4,
    gae_lambda=0.95,
    grad_clip=0.5,
)
# the paper's PPO settings per env: its table, and what its runs used beyond the table
# (the critic's rate and optimiser, GAE's lambda, rayleigh's wider networks)
PPO = {
    "shkadov-v0": dict(n_rollout=3200, frames=200_000, critic_optim="nadam"),
    "rayleigh-v0": dict(n_rollout=1000, frames=600_000, entropy=0.001, hidden=128),
    # mixing's step costs most of its training: two collector processes use both cores
    "mixing-v0": dict(n_rollout=2000, frames=100_000, gae_lambda=0.90, collectors=2),
    "lorenz-v0": dict(n_rollout=10_000, frames=2_000_000, entropy=0.005),
    "burgers-v0": dict(n_rollout=4000, frames=500_000, critic_lr=1e-3),
    # its episodes all start from one stored state, so few members in step each cover
    # more of an episode per rollout
    "sloshing-v0": dict(n_rollout=2000, epochs=16, frames=200_000, critic_lr=1e-3, num_envs=4),
    # vortex alone normalises its observations (the paper's library ignored the setting
    # and its runs stayed at a lower score)
    "vortex-v0": dict(n_rollout=4000, frames=1_000_000, critic_lr=1e-3, norm_steps=64),
    # beyond the paper: Rabault et al.'s agent (512-wide networks, both rates 1e-3, 20
    # episodes of 80 actions per update, 25 minibatch steps of a fifth of them, GAE's
    # lambda 0.97)
    "cylinder-v0": RABAULT,
    # beyond the paper: the cylinder's agent, 16 episodes of 100 actions per update
    "pinball-v0": RABAULT,
    # beyond the paper: its trials levelled off by 2 million transitions (670 episodes)
    "ks-v0": dict(frames=2_000_000),
    # beyond the paper: Vignon et al.'s budget on their channel, 350 episodes of the flow
    # (200 actions each, every action a transition of each of the 10 agents), with
    # rayleigh-v0's settings of the paper otherwise
    "rayleigh-separable-v0": dict(n_rollout=1000, frames=70_000, entropy=0.001, hidden=128),
    # beyond the paper: FluidGym's runs on its RBC2D levels (the same settings at each)
    **{f"rbc2d-{level}-v0": FLUIDGYM_PPO for level in RBC2D_LEVELS},
    # its multi-agent runs: each agent a member of Stable-Baselines3's vector env, so a
    # rollout of 2,048 flow steps holds 2,048 transitions of each agent, in minibatches
    # of 64 agent transitions; here a minibatch is 8 flow steps of the 12 agents (96)
    **{f"rbc2d-{level}-ma-v0": dict(FLUIDGYM_PPO, minibatches=256) for level in RBC2D_LEVELS},
}
# TD3, where its settings differ from the paper's agent
TD3 = {
    # burgers' sensors hardly differ between states: normalised, and exploring with the
    # noise of the paper's DDPG runs
    "burgers-v0": dict(norm_steps=64, exploration_sigma=0.01),
    # a jet's push shows in shkadov's reward tens of actions later: multi-step targets
    "shkadov-v0": dict(n_steps=20),
    # an update after every step makes ks' 3,000-action episodes slow to collect: a trial
    # had not started to learn after 100,000 transitions, twice that is the budget
    "ks-v0": dict(frames=200_000),
}
# SAC: the budgets at which TD3's results are recorded (docs/results.md), so that the
# two off-policy recipes compare at equal transitions; burgers normalised as for TD3
SAC = {
    "lorenz-v0": dict(frames=100_000),
    "vortex-v0": dict(frames=100_000),
    "burgers-v0": dict(frames=100_000, norm_steps=64),
    "sloshing-v0": dict(frames=100_000),
    "rayleigh-v0": dict(frames=19_200),
    "mixing-v0": dict(frames=8_192),
    # FluidGym's runs on its RBC2D levels (Stable-Baselines3's SAC: a buffer of the whole
    # run, batches of 256, a gradient step a transition, 100 random transitions first;
    # the same settings at each level)
    **{f"rbc2d-{level}-v0": dict(frames=50_000, batch_size=256, init_random_frames=100) for level in RBC2D_LEVELS},
    # multi-agent: Stable-Baselines3's vector env of the 12 agents counts its buffer (50,000)
    # and its random start (100) in agent transitions, so here in flow steps of the 12
    # (the whole run's flow steps would hold twelve times its buffer, 6.8 GB); a gradient
    # step per agent transition, each on 21 flow steps (252 agent transitions; its 256)
    **{
        f"rbc2d-{level}-ma-v0": dict(
            frames=50_000,
            buffer_size=50_000 // 12,
            batch_size=21,
            updates_per_batch=12 * 64,
            init_random_frames=-(-100 // 12),
        )
        for level in RBC2D_LEVELS
    },
    # beyond TD3's table: the gradient recipe's budget on the cylinder
    "cylinder-v0": dict(frames=16_000),
}
# the first-order loop (gradient-based control and the short-horizon actor-critic: one
# table, so that the two differ only by the critic), where its settings differ from the
# defaults. Its budget is a tenth of PPO's: where 64 members x 32 actions leave too few
# updates in it (9 on sloshing and shkadov, 97 on lorenz and ks), 16 members, which
# trials of one seed measured to learn further in the budget (ks by the same rule,
# untried). Lorenz's reward counts steps in a lobe and has no gradient: it is trained on
# the indicator's value with a smooth step's gradient. The 2-D flows, whose
# differentiated action holds gigabytes, with fewer members and, where the memory calls
# for it, each action recomputed in the backward pass.
FIRST_ORDER = {
    "lorenz-v0": dict(num_envs=16, params={"reward_width": 1.0, "reward_value": "indicator"}),
    "sloshing-v0": dict(num_envs=16, horizon=16),
    "shkadov-v0": dict(num_envs=16),
    "ks-v0": dict(num_envs=16),
    "vortex-v0": dict(grad_checkpoint=True, stagger=True),
    # compiled: eagerly a differentiated action measured 28 (rayleigh) and 25 (mixing)
    # times the compiled forward one. With the substeps' adjoint written out an action
    # keeps its fields, not a graph: a horizon of rayleigh kept whole peaks at 1.35 GiB,
    # mixing's at 4.3 GiB (2.8 to 3.0 times the forward), and with its first 12 actions
    # of 16 kept whole at 3.6 GiB (3.2 to 3.5 times, against 4.2 recomputed)
    "rayleigh-v0": dict(num_envs=8, horizon=16, compile=True),
    "mixing-v0": dict(num_envs=8, horizon=16, grad_checkpoint=True, grad_checkpoint_after=12, compile=True),
    # the wakes compiled: an update of 20 actions took a third (the cylinder) and a fifth
    # (the pinball) of the eager one's time and a quarter of its memory, with the same
    # numbers to float32 round-off; the cylinder's compiled horizon kept whole (16
    # actions at 8 members: 2.6 GiB at the process's peak against 0.95 recomputed; 3.8
    # times the forward against 5.0), the pinball's actions recomputed but for the first
    # 10 of a horizon
    "cylinder-v0": dict(num_envs=8, horizon=20, compile=True),
    # the pinball's first 10 actions of a horizon kept whole and the rest recomputed: 16
    # actions at 8 members peak at 3.5 GiB and cost 2.6 times the compiled forward (all
    # kept whole: 4.8 GiB, 2.2 times; all recomputed: 1.1 GiB, 3.3 times)
    "pinball-v0": dict(num_envs=8, horizon=20, grad_checkpoint=True, grad_checkpoint_after=10, compile=True),
}

# domains of settings: (lowest, highest, whether the lowest itself is excluded)
POSITIVE = (0.0, math.inf, True)
NON_NEGATIVE = (0.0, math.inf, False)
# a seed torch's generators take (a signed 64-bit integer's positive half)
SEEDS = (0, 2**63 - 1, False)
# the widths of hidden layers that evaluation, the curves and a resume rebuild
WIDTHS = (1, MAX_HIDDEN, False)


def setting(
    default,
    help: str,
    choices: tuple[str, ...] = (),
    domain: tuple[float, float, bool] | None = None,
    flag: str = "",
):
    """A field of a recipe's settings: its default, its help, and what is admissible
    (``choices``, or a ``domain`` of numbers); ``flag``: the command line's name of a
    dict field given as repeated NAME=VALUE options."""
    metadata = {"help": help, "choices": choices, "domain": domain, "flag": flag}
    if isinstance(default, dict):
        return field(default_factory=dict, metadata=metadata)
    return field(default=default, metadata=metadata)


def redefault(cls: type, name: str, default):
    """``cls``'s setting ``name`` with another default, for a subclass: its help and
    domain said once."""
    return setting(default, **{k: v for k, v in next(f for f in fields(cls) if f.name == name).metadata.items()})


@dataclass(frozen=True, kw_only=True)
class Settings:
    """The settings of every recipe's command line, training or not: the env and its
    parameters, the members, the seed, the device, the threads, where it writes."""

    algo: ClassVar[str]
    # which actions the algorithm acts with: "any", "continuous" or "discrete"
    action_kind: ClassVar[str] = "any"
    # whether it trains the multi-agent layout (one policy shared by the agents)
    multi_agent: ClassVar[bool] = False
    # more fields that must be positive integers
    positive: ClassVar[tuple[str, ...]] = ()
    # per-env defaults (env id -> field values); a variant reads its base env's entry
    table: ClassVar[dict[str, dict]] = {}
    # whether a run trains a policy, logs it and draws its learning curve
    trains: ClassVar[bool] = True
    # where a run writes by default ({algo}, {env}, {seed} filled in)
    default_out: ClassVar[str] = "runs/{algo}/{env}/seed{seed}"
    # the files a run creates in OUT and never overwrites (a training's run directory
    # is checked as a whole when the run starts)
    creates: ClassVar[tuple[str, ...]] = ()

    env: str = setting("", "environment id (beacon-torch list)")
    # the env's physical parameters (beacon-torch list), recorded with the checkpoints,
    # so that evaluations and exported policies rebuild the env that was trained
    params: dict = setting({}, "an env parameter as NAME=VALUE (repeatable)", flag="--param")
    seed: int = setting(0, "seed of the networks, the env and the collection", domain=SEEDS)
    num_envs: int = setting(8, "members of the batched env collecting together")
    device: str = setting("cpu", "torch device of the env and the networks")
    out: str = setting("", "run directory")
    progress: bool = setting(True, "progress bar")
    threads: int = setting(
        0,
        "torch threads, at most this machine's cores (0: $BEACON_TORCH_THREADS, else the count measured fastest "
        "for training on the env on an idle machine; on a shared machine give 1)",
    )


@dataclass(frozen=True, kw_only=True)
class Config(Settings):
    """The settings every training recipe shares."""

    # the field holding the transitions collected per round, a multiple of the members
    batch: ClassVar[str] = "num_envs"
    # whether the algorithm needs the env in its own process (no collectors, no Ray)
    in_process: ClassVar[bool] = False
    # the default budget, as a share of the paper's PPO budget of the env
    budget_share: ClassVar[float] = 1.0

    frames: int = setting(200_000, "total transitions")
    hidden: int = setting(64, "width of the hidden layers", domain=WIDTHS)
    gamma: float = setting(0.99, "discount", domain=(0.0, 1.0, True))
    # one compiled call per action: faster collection for a compilation at the start
    # (docs/performance.md)
    compile: bool = setting(
        True, "the env's compiled physics (--no-compile: eager; BEACON_TORCH_COMPILE=0 turns this default off)"
    )
    norm_steps: int = setting(
        0,
        f"random steps whose observations set a normalisation (0: raw observations, as the paper's "
        f"agents saw them; {NORM_STEPS} reach past every env's start-up)",
    )
    starts: str = setting(
        "",
        "start the training episodes from the train set of developed states (beacon_torch.starts; "
        "'': the env's own start, the paper's)",
        ("", "train"),
    )
    resume: bool = setting(False, "continue the run in OUT from its checkpoint to FRAMES")
    collectors: int = setting(1, "collector processes (or Ray actors), each with a batched env of NUM_ENVS members")
    ray: str = setting(
        "",
        "collect with Ray actors on the cluster at this address ('auto', or 'local' for one here); "
        "needs beacon-torch[ray]",
    )
    logger: str = setting(
        "auto",
        "'csv', 'tensorboard' (CSV and TensorBoard), 'wandb' (CSV and Weights & Biases; offline with "
        "WANDB_MODE=offline), 'mlflow' (CSV and MLflow, to $MLFLOW_TRACKING_URI or OUT/mlflow.db) or 'auto' "
        "(TensorBoard too when installed)",
        ("auto", "csv", "tensorboard", "wandb", "mlflow"),
    )
    checkpoint_every: int = setting(10, "rounds of updates between two checkpoints")

    @property
    def tensorboard(self) -> bool | None:
        return {"auto": None, "csv": False, "tensorboard": True}.get(self.logger, False)

    @property
    def tracker(self) -> str:
        """The experiment tracker beside the CSV logs: "wandb", "mlflow" or ""."""
        return self.logger if self.logger in ("wandb", "mlflow") else ""

    def per_round(self) -> int:
        """The transitions collected per round of updates: a run collects whole rounds."""
        return getattr(self, self.batch)


@dataclass(frozen=True, kw_only=True)
class PPOConfig(Config):
    """PPO (any action space, the multi-agent layout included)."""

    algo: ClassVar[str] = "ppo"
    multi_agent: ClassVar[bool] = True
    table: ClassVar[dict[str, dict]] = PPO
    batch: ClassVar[str] = "n_rollout"
    positive: ClassVar[tuple[str, ...]] = ("n_rollout", "minibatches", "epochs")

    # the members of the recorded PPO campaign; an update's rollout holds n_rollout
    # transitions however many members collect them
    num_envs: int = setting(16, "members of the batched env collecting together")
    n_rollout: int = setting(2000, "transitions collected between two updates")
    minibatches: int = setting(2, "minibatches per epoch")
    epochs: int = setting(32, "passes over each collected batch")
    gae_lambda: float = setting(0.99, "GAE's lambda", domain=(0.0, 1.0, False))
    actor_lr: float = setting(5e-4, "actor learning rate (Adam)", domain=POSITIVE)
    critic_lr: float = setting(5e-3, "critic learning rate", domain=POSITIVE)
    critic_optim: str = setting("adam", "the critic's optimiser: 'adam' or 'nadam'", ("adam", "nadam"))
    clip: float = setting(0.2, "PPO's clipping of the probability ratio", domain=POSITIVE)
    entropy: float = setting(0.01, "entropy bonus", domain=NON_NEGATIVE)
    grad_clip: float = setting(0.1, "clipping of each network's gradient norm", domain=POSITIVE)
    actor: str = setting(
        "paper",
        "the actor: 'paper' (the paper's agent: bounded mean and spread heads, a spread starting at "
        "0.5) or 'free-spread' (Stable-Baselines3's: an unbounded mean, one learned spread per action "
        "starting at 1); continuous actions",
        ("paper", "free-spread"),
    )
    critic: str = setting(
        "paper",
        "the critic: 'paper' (two ReLU layers, the output zero) or 'sb3' (Stable-Baselines3's: two tanh layers, "
        "orthogonal with gain sqrt(2), the output's gain 1)",
        ("paper", "sb3"),
    )
    update: str = setting(
        "paper",
        "the update: 'paper' (advantages normalised over the rollout; each network's gradient clipped alone) or "
        "'sb3' (Stable-Baselines3's: advantages normalised per minibatch, the value error weighted 0.5, the two "
        "networks' gradient clipped as one, Adam's epsilon 1e-5)",
        ("paper", "sb3"),
    )


@dataclass(frozen=True, kw_only=True)
class OffPolicyConfig(Config):
    """What TD3 and DQN share: a replay buffer filled by a collector, a number of
    gradient steps per collected batch, soft target updates."""

    batch: ClassVar[str] = "frames_per_batch"
    positive: ClassVar[tuple[str, ...]] = ("frames_per_batch", "batch_size", "updates_per_batch")

    frames_per_batch: int = setting(64, "transitions collected between two rounds of updates")
    buffer_size: int = setting(0, "replay buffer capacity in transitions (0: the whole run)")
    batch_size: int = setting(64, "transitions per gradient step")
    updates_per_batch: int = setting(64, "gradient steps per collected batch (the paper's agents: one per transition)")


@dataclass(frozen=True, kw_only=True)
class TD3Config(OffPolicyConfig):
    """TD3 (continuous actions)."""

    algo: ClassVar[str] = "td3"
    action_kind: ClassVar[str] = "continuous"
    table: ClassVar[dict[str, dict]] = TD3
    positive: ClassVar[tuple[str, ...]] = (*OffPolicyConfig.positive, "n_steps")

    hidden: int = setting(128, "width of the hidden layers", domain=WIDTHS)
    init_random_frames: int = setting(1_000, "uniformly random actions before the policy acts", domain=NON_NEGATIVE)
    lr: float = setting(
        1e-3, "learning rate of the critics, and of the actor unless ACTOR_LR is given (Adam)", domain=POSITIVE
    )
    actor_lr: float = setting(0.0, "learning rate of the actor (0: LR, as in the paper's agent)", domain=NON_NEGATIVE)
    tau: float = setting(0.02, "soft update of the target networks", domain=(0.0, 1.0, True))
    policy_noise: float = setting(0.002, "target policy smoothing noise, in action units", domain=NON_NEGATIVE)
    noise_clip: float = setting(0.005, "clipping of the smoothing noise", domain=NON_NEGATIVE)
    exploration_sigma: float = setting(0.001, "Gaussian exploration noise, in action units", domain=NON_NEGATIVE)
    n_steps: int = setting(1, "transitions summed into each critic target (1: the paper's agent)")


@dataclass(frozen=True, kw_only=True)
class SACConfig(OffPolicyConfig):
    """SAC (continuous actions): twin critics and their targets, a squashed Gaussian
    actor, the entropy's weight tuned to a target entropy."""

    algo: ClassVar[str] = "sac"
    multi_agent: ClassVar[bool] = True
    action_kind: ClassVar[str] = "continuous"
    table: ClassVar[dict[str, dict]] = SAC

    hidden: int = setting(256, "width of the hidden layers", domain=WIDTHS)
    init_random_frames: int = setting(1_000, "uniformly random actions before the policy acts", domain=NON_NEGATIVE)
    lr: float = setting(3e-4, "learning rate of the actor and the critics (Adam)", domain=POSITIVE)
    alpha_lr: float = setting(3e-4, "learning rate of the entropy's weight", domain=POSITIVE)
    alpha_init: float = setting(1.0, "the entropy's weight at the start", domain=POSITIVE)
    tau: float = setting(0.005, "soft update of the target critics", domain=(0.0, 1.0, True))


@dataclass(frozen=True, kw_only=True)
class DQNConfig(OffPolicyConfig):
    """DQN (discrete actions)."""

    algo: ClassVar[str] = "dqn"
    action_kind: ClassVar[str] = "discrete"
    positive: ClassVar[tuple[str, ...]] = (*OffPolicyConfig.positive, "target_every")

    init_random_frames: int = setting(0, "uniformly random actions before the policy acts", domain=NON_NEGATIVE)
    lr: float = setting(5e-4, "learning rate (Adam)", domain=POSITIVE)
    target_every: int = setting(50, "updates between two copies of the network into the target")
    eps_init: float = setting(0.5, "initial exploration rate", domain=(0.0, 1.0, False))
    eps_end: float = setting(0.05, "final exploration rate", domain=(0.0, 1.0, False))
    eps_frames: int = setting(
        2_000_000, "transitions over which the exploration rate anneals linearly", domain=POSITIVE
    )


@dataclass(frozen=True, kw_only=True)
class GradConfig(Config):
    """Gradient-based control: a deterministic policy trained by backpropagating the
    rewards of ``horizon`` steps through the physics (one process: no collectors). No
    critic: the short-horizon actor-critic's critic-less setting."""

    algo: ClassVar[str] = "grad"
    action_kind: ClassVar[str] = "continuous"
    table: ClassVar[dict[str, dict]] = FIRST_ORDER
    # what it is to show: PPO's score in a tenth of PPO's transitions
    budget_share: ClassVar[float] = 0.1
    in_process: ClassVar[bool] = True
    positive: ClassVar[tuple[str, ...]] = ("horizon", "horizon_min", "horizon_max", "estimator_groups")
    # whether a critic's value closes each horizon
    critic: ClassVar[bool] = False

    # 16 members: four times the updates of 64 in a tenth of PPO's transitions, each an
    # average over members spread across the episode (vortex 1.42 to 1.50 against 0.60 to
    # 1.01 at 64, burgers 1.79 against 1.73; docs/gradients.md's table of settings)
    num_envs: int = setting(16, "members of the batched env")
    norm_steps: int = setting(NORM_STEPS, "random steps whose observations set the normalisation (0: raw observations)")
    horizon: int = setting(32, "differentiated steps per update (the graph is cut between updates)")
    # 1e-2: mixing 1.28 on three seeds against 0.82 at 5e-3, level on burgers, vortex and
    # sloshing; shkadov 1.08 against 1.23 and lorenz-continuous 0.57 against 0.80
    # (docs/gradients.md's table of settings)
    lr: float = setting(1e-2, "the policy's learning rate", domain=POSITIVE)
    grad_clip: float = setting(1.0, "clipping of the policy's gradient norm", domain=POSITIVE)
    lr_schedule: str = setting(
        "constant",
        "the learning rates over the run: constant, or linear (SHAC's: from their values down to 1e-5 at the "
        "run's last transition, the policy's and the critics' alike)",
        ("constant", "linear"),
    )
    optimizer: str = setting(
        "adam", "the policy's (and critics') optimiser; adamw: SAPO's, betas 0.7 and 0.95", ("adam", "adamw")
    )
    actor: str = setting(
        "deterministic",
        "the policy: deterministic, or stochastic (SAPO's: a normal draw squashed into the action box, "
        "reparametrised, with a tuned entropy bonus)",
        ("deterministic", "stochastic"),
    )
    target_entropy: float = setting(
        -0.5,
        "a stochastic policy's target entropy per action dimension, towards which alpha is tuned",
        domain=(-math.inf, math.inf, True),
    )
    layer_norm: bool = setting(
        False, "hidden layers of linear, LayerNorm and SiLU (SAPO's) in the policy and the critics, not ReLU"
    )
    adaptive_horizon: bool = setting(
        False,
        "adapt the horizon after each update: shorter while the objective's gradient with respect to its first "
        "action is more than HORIZON_GROWTH times that with respect to its last, longer otherwise",
    )
    estimator: str = setting(
        "first-order",
        "the policy's gradient: first-order (through the physics), or mixed with the likelihood ratio's by their "
        "variances (a stochastic policy; a backward pass per group of members)",
        ("first-order", "mixed"),
    )
    estimator_groups: int = setting(4, "the mixed estimator's groups of members, whose spread gives the variances")
    horizon_growth: float = setting(10.0, "the adaptive horizon's bound on the gradient's growth", domain=POSITIVE)
    horizon_min: int = setting(8, "the adaptive horizon's shortest")
    horizon_max: int = setting(64, "the adaptive horizon's longest")
    init_alpha: float = setting(1.0, "the entropy bonus's first weight alpha", domain=POSITIVE)
    alpha_lr: float = setting(5e-3, "the learning rate of log alpha", domain=POSITIVE)
    grad_checkpoint: bool = setting(False, "recompute each action in the backward pass (long horizons)")
    grad_checkpoint_after: int = setting(
        0,
        "with grad_checkpoint, the actions of a horizon whose graphs are kept whole before the later ones are "
        "recomputed (memory for time)",
        domain=NON_NEGATIVE,
    )
    # without a critic the policy's actions drifted to the box's edges, where the squash
    # passes no gradient, on rayleigh and vortex (docs/gradients.md's table of settings)
    squash_margin: float = setting(
        0.01,
        "a quadratic barrier on the deterministic policy's pre-squash outputs past atanh(1 - SQUASH_MARGIN), "
        "where its actions come within that share of the half-width of the box's edges and tanh passes almost "
        "none of the physics' gradient back (0: none)",
        domain=(0.0, 0.5, False),
    )
    # from torch's random policy a seed of vortex settled on the low cycle or the high one
    # by its first episodes; from near no control every seed reached the high one
    init_scale: float = setting(
        0.01,
        "the factor on the deterministic policy's output layer at initialisation (1: torch's): near 0 every "
        "seed starts near no control and its first updates follow the physics' gradient there",
        domain=NON_NEGATIVE,
    )
    member_scale: bool = setting(
        False,
        "divide each member's objective by the mean size of its rewards over the horizon, so that members in "
        "quiet phases of their episodes weigh as much as members in loud ones",
    )
    # from one start a deterministic policy steps the members of a deterministic env in
    # lockstep: the same transitions many times over, and every update follows one phase
    # of the episode (sloshing 0.93 staggered against 0.84, docs/gradients.md's settings)
    stagger: bool = setting(
        True,
        "cut each member's first episode after a random number of actions, so that the members "
        "spread over an episode's phases instead of all being at the same instant",
    )
    # a differentiated step compiles in chunks of substeps (a small action as one graph),
    # not as one call; the tables turn it on where it was measured to pay. The recorded
    # runs elsewhere are eager
    compile: bool = setting(False, "the env's compiled physics")

    def per_round(self) -> int:
        return self.num_envs * self.horizon


@dataclass(frozen=True, kw_only=True)
class SHACConfig(GradConfig):
    """The short-horizon actor-critic (SHAC, Xu et al. 2022): gradient-based control whose
    horizons are closed by a critic's value, the critic fitted to TD(lambda) targets of
    the states the horizons went through."""

    algo: ClassVar[str] = "shac"
    positive: ClassVar[tuple[str, ...]] = (*GradConfig.positive, "critic_iterations", "critic_minibatches", "critics")
    critic: ClassVar[bool] = True

    # the seeds published ran without the squash's margin, which measured level with a
    # critic on burgers, vortex and sloshing
    squash_margin: float = redefault(GradConfig, "squash_margin", 0.0)
    # and in lockstep but on vortex, where staggering was measured first
    stagger: bool = redefault(GradConfig, "stagger", False)
    # and with 64 members, the rate 2e-3 and torch's initialisation of the policy
    num_envs: int = redefault(GradConfig, "num_envs", 64)
    lr: float = redefault(GradConfig, "lr", 2e-3)
    init_scale: float = redefault(GradConfig, "init_scale", 1.0)
    critic_lr: float = setting(1e-3, "the critic's learning rate", domain=POSITIVE)
    lmbda: float = setting(0.95, "lambda of the critic's TD(lambda) targets", domain=(0.0, 1.0, False))
    critic_iterations: int = setting(16, "passes over a horizon's states fitting the critic")
    critic_minibatches: int = setting(4, "minibatches per pass")
    target_alpha: float = setting(
        0.2,
        "the target critic keeps this share of itself at each update (the rest: the critic)",
        domain=(0.0, 1.0, False),
    )
    critics: int = setting(
        1, "critics fitted side by side; their mean value closes the horizons, the lowest their targets (SAPO: 2)"
    )
    target_critic: bool = setting(
        True, "close the horizons and the targets with a slowly following copy of the critics (SAPO: without)"
    )
    value_weight: float = setting(
        1.0,
        "the weight of the critic's value where it closes a return, in the policy's objective (1: SHAC's; 0: the "
        "rewards alone, the critic still fitted)",
        domain=(0.0, 1.0, False),
    )
    gradient_split: bool = setting(
        False,
        "log the policy's gradient through the closing values and through the rest apart (their norms, their "
        "cosine, the values' share of the objective); one more backward pass an update",
    )


@dataclass(frozen=True, kw_only=True)
class MPCConfig(Settings):
    """Gradient model-predictive control (no learned policy): before each action, the
    next HORIZON actions of every member are improved by ITERATIONS steps of gradient
    ascent on their predicted return, differentiated through the physics."""

    algo: ClassVar[str] = "mpc"
    action_kind: ClassVar[str] = "continuous"
    positive: ClassVar[tuple[str, ...]] = ("horizon", "iterations", "checkpoint_every")
    trains: ClassVar[bool] = False
    default_out: ClassVar[str] = "runs/mpc/{env}"
    creates: ClassVar[tuple[str, ...]] = ("mpc.json",)

    plan_params: dict = setting(
        {},
        "a parameter of the planner's model only, as NAME=VALUE (lorenz's reward_width=1: a smooth stand-in for "
        "its indicator reward, whose gradient is zero); the episodes are judged by the env's own",
        flag="--plan-param",
    )
    horizon: int = setting(20, "actions planned ahead")
    iterations: int = setting(10, "gradient steps per action")
    lr: float = setting(0.1, "Adam's rate on the actions, which lie in [-1, 1]", domain=POSITIVE)
    discount: float = setting(1.0, "of the predicted rewards", domain=(0.0, 1.0, True))
    starts: str = setting(HELD_OUT, "the evaluation episodes' starts", ("own", "validation", "test"))
    num_envs: int = setting(8, "evaluation episodes, one member each")
    actions: int = setting(0, "plan this many actions only, for their cost (0: whole episodes)", domain=NON_NEGATIVE)
    grad_checkpoint: bool = setting(False, "recompute each action in the backward pass")
    compile: bool = setting(False, "the env's compiled physics")
    seed: int = setting(0, "of the planner's noise", domain=SEEDS)
    out: str = setting("", "the folder of mpc.json")
    checkpoint_every: int = setting(
        10, "planned actions between two saves of the episodes under way (OUT/mpc-checkpoint.pt)"
    )
    resume: bool = setting(False, "go on with the planned episodes saved in OUT")


CONFIGS = {cls.algo: cls for cls in (PPOConfig, TD3Config, SACConfig, DQNConfig, GradConfig, SHACConfig)}


def unfit(cls: type[Settings], env: EnvSpec) -> str | None:
    """Why ``cls``'s algorithm cannot control ``env`` (its actions, its agents), or None."""
    trainer = issubclass(cls, Config)
    if cls.action_kind == "continuous" and env.physics.discrete:
        twin = next((e for e in continuous_envs() if ENVS[e].base_id() == env.base_id()), None)
        hint = f" (use ppo or dqn{f', or {twin}' if twin else ''})" if trainer else (f" (use {twin})" if twin else "")
        return f"{cls.algo} needs continuous actions; {env.env_id} has discrete ones{hint}"
    if cls.action_kind == "discrete" and not env.physics.discrete:
        return f"{cls.algo} needs discrete actions; {env.env_id} has continuous ones (use ppo or td3)"
    if env.agents is not None and not cls.multi_agent:
        single = env.base_id() if env.base_id() != env.env_id else "its single-agent layout"
        capable = " or ".join(c.algo for c in CONFIGS.values() if c.multi_agent)
        use = f"use {capable}, or {single}" if trainer else f"use {single}"
        return f"{cls.algo} controls single-agent layouts; {env.env_id} has one agent per {env.agents} ({use})"
    return None


def paper_algorithms(env_id: str) -> tuple[str, ...]:
    """The algorithms the paper trains on an env: PPO on every one, TD3 where the actions
    are continuous and DQN where they are discrete, on single-agent layouts."""
    env = env_spec(env_id)
    return tuple(cls.algo for cls in (PPOConfig, TD3Config, DQNConfig) if unfit(cls, env) is None)


def table_entry(table: dict[str, dict], env_id: str) -> dict:
    """``env_id``'s entry of a settings table: its own, else that of the env it is a
    variant of, and so on (a level's multi-agent layout trains like the level)."""
    spec = env_spec(env_id)
    while spec.env_id not in table and spec.base_id() != spec.env_id:
        spec = env_spec(spec.base_id())
    return table.get(spec.env_id, {})


def paper_frames(env_id: str) -> int:
    """The paper's PPO budget of ``env_id``, the default budget of every algorithm."""
    return table_entry(PPO, env_id).get("frames", Config.frames)


def defaults(cls: type[Settings], env_id: str) -> dict:
    """The per-env defaults of an algorithm: its share of the paper's PPO budget (a
    training's), then the entry of the algorithm's own table."""
    # BEACON_TORCH_COMPILE=0 turns a table's compilation off too
    off = {} if compiles_by_default() else {"compile": False}
    budget = {"frames": int(paper_frames(env_id) * cls.budget_share)} if issubclass(cls, Config) else {}
    return {**budget, **table_entry(cls.table, env_id), **off}


def _typed(name: str, kind: str, value):
    """A setting given as text or number (``compile="true"``, ``epochs=8.0``) in its
    field's type, or a clear error."""
    if kind == "bool":
        if isinstance(value, str):
            value = {"true": 1, "false": 0}.get(value.lower(), value)
        if value in (0, 1):
            return bool(value)
    elif (
        kind == "int"
        and isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and float(value).is_integer()
    ):
        return int(value)
    elif kind == "float" and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    elif kind == "str" and isinstance(value, str):
        return value
    elif kind == "dict" and isinstance(value, dict) and all(isinstance(k, str) for k in value):
        return dict(value)
    raise ValueError(f"setting '{name}' must be of type {kind}, got {value!r}")


def _domain_text(low: float, high: float, open_low: bool, integer: bool) -> str:
    kind = "an integer" if integer else "finite and"
    if math.isfinite(high):
        shown = (f"{int(low)}", f"{int(high)}") if integer else (f"{low:g}", f"{high:g}")
        return f"{kind} in {'(' if open_low else '['}{shown[0]}, {shown[1]}]"
    if integer:
        return "a positive integer" if (low > 0 or open_low) else "a non-negative integer"
    return f"{kind} {'>' if open_low else '>='} {low:g}"


def _wandb_ready() -> bool:
    """Whether Weights & Biases can log without asking for a key: offline or disabled,
    a key in the environment, or a login saved in ~/.netrc."""
    if os.environ.get("WANDB_MODE", "").lower() in ("offline", "disabled", "dryrun") or os.environ.get("WANDB_API_KEY"):
        return True
    try:
        import netrc

        return netrc.netrc().authenticators("api.wandb.ai") is not None
    except (OSError, netrc.NetrcParseError):
        return False


def check_settings(cfg: Settings) -> Settings:
    """Refuse, in one line naming the setting and what it admits, settings that a run or
    a tool reading it later would refuse or fail on: what every recipe shares."""
    threads.check(cfg.threads, "setting 'threads'", zero="the measured default")
    threads.choose(cfg.threads or None)  # $BEACON_TORCH_THREADS too
    for name in ("num_envs", *cfg.positive):
        if getattr(cfg, name) < 1:
            raise ValueError(f"setting '{name}' must be a positive integer, got {getattr(cfg, name)}")
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        if f.metadata["domain"] is not None:
            low, high, open_low = f.metadata["domain"]
            if not (math.isfinite(value) and (value > low if open_low else value >= low) and value <= high):
                where = _domain_text(low, high, open_low, f.type == "int")
                raise ValueError(f"setting '{f.name}' must be {where}, got {value!r}")
        if f.metadata["choices"] and value not in f.metadata["choices"]:
            raise ValueError(
                f"setting '{f.name}' must be one of {', '.join(map(repr, f.metadata['choices']))}, got {value!r}"
            )
    env = beacon_torch.registry.env_spec(cfg.env)
    for f in fields(cfg):
        if f.type == "dict":
            try:
                env.check({**cfg.params, **getattr(cfg, f.name)})
            except (TypeError, ValueError) as err:
                raise ValueError(f"setting '{f.name}' ({f.metadata['flag']}): {err}") from None
    as_device(cfg.device)
    reason = unfit(type(cfg), env)
    if reason:
        raise ValueError(reason)
    out = Path(cfg.out)
    if out.is_symlink() and not out.exists():
        raise ValueError(f"setting 'out': {out} is a symbolic link to nothing; give a directory")
    if out.exists() and not out.is_dir():
        raise ValueError(f"setting 'out': {out} is a file, not a directory; give a directory")
    for name in cfg.creates:
        if (out / name).exists() or (out / name).is_symlink():
            raise ValueError(f"setting 'out': {out / name} exists and is not overwritten; give another --out")
    return cfg


def _check(cfg: Settings) -> Settings:
    check_settings(cfg)
    if not isinstance(cfg, Config):
        return cfg
    if cfg.in_process and (cfg.collectors != 1 or cfg.ray):
        raise ValueError(f"{cfg.algo} differentiates through the env in this process: collectors and ray do not apply")
    if cfg.norm_steps < 0:
        raise ValueError(
            f"setting 'norm_steps' must be 0 (raw observations) or a positive integer, got {cfg.norm_steps}"
        )
    for name in ("frames", "collectors", "checkpoint_every"):
        if getattr(cfg, name) < 1:
            raise ValueError(f"setting '{name}' must be a positive integer, got {getattr(cfg, name)}")
    if isinstance(cfg, GradConfig) and cfg.estimator == "mixed":
        if cfg.actor != "stochastic":
            raise ValueError("the mixed estimator needs a stochastic policy's likelihood: give actor=stochastic")
        if cfg.adaptive_horizon:
            raise ValueError(
                "the adaptive horizon reads the first-order gradient's own pass: not with the mixed estimator"
            )
        if not 2 <= cfg.estimator_groups <= cfg.num_envs:
            raise ValueError(
                f"the mixed estimator's groups ({cfg.estimator_groups}) must number 2 to the members ({cfg.num_envs})"
            )
    if isinstance(cfg, GradConfig) and cfg.squash_margin and cfg.actor != "deterministic":
        raise ValueError("squash_margin bounds the deterministic policy's squash: not with actor=stochastic")
    if isinstance(cfg, GradConfig) and cfg.adaptive_horizon and not cfg.horizon_min <= cfg.horizon <= cfg.horizon_max:
        raise ValueError(
            f"the adaptive horizon starts within its bounds: horizon_min ({cfg.horizon_min}) <= horizon "
            f"({cfg.horizon}) <= horizon_max ({cfg.horizon_max})"
        )
    members = cfg.num_envs * cfg.collectors
    if cfg.frames < getattr(cfg, cfg.batch):
        raise ValueError(
            f"frames ({cfg.frames}) must be at least one collected batch, {cfg.batch} ({getattr(cfg, cfg.batch)})"
        )
    if getattr(cfg, cfg.batch) % members:
        raise ValueError(
            f"{cfg.batch} ({getattr(cfg, cfg.batch)}) must be a multiple of the members collecting it, num_envs x "
            f"collectors ({cfg.num_envs} x {cfg.collectors} = {members})"
        )
    if cfg.logger == "wandb" and find_spec("wandb") is not None and not _wandb_ready():
        raise ValueError(
            "setting 'logger' = 'wandb' needs a Weights & Biases key (wandb login, or $WANDB_API_KEY), or "
            "WANDB_MODE=offline to log into the run directory only"
        )
    env = beacon_torch.registry.env_spec(cfg.env)
    # a collected batch is held whole (with the advantages, for PPO)
    fits(
        f"a collected batch of {cfg.per_round():,} transitions", 2 * cfg.per_round() * transition_bytes(env, cfg.params)
    )
    if isinstance(cfg, OffPolicyConfig):
        # the replay buffer is allocated whole at the first transition: refused now if
        # it cannot fit
        if cfg.buffer_size < 0:
            raise ValueError(f"setting 'buffer_size' must be 0 (the whole run) or positive, got {cfg.buffer_size}")
        capacity = cfg.buffer_size or cfg.frames
        need = capacity * transition_bytes(env, cfg.params)
        fits(f"a replay buffer of {capacity:,} transitions", need, cfg.device)
    return cfg


def transition_bytes(env: EnvSpec, params: dict) -> int:
    """About the bytes one stored transition of ``env`` takes in a replay buffer: the
    observation before and after, the action and the policy's output, rewards and
    returns (float32), the end flags and the trajectory's id."""
    n_obs, n_actions = env.sizes(params)
    return 4 * (2 * n_obs + 3 * n_actions + 4) + 6 + 8


def configure(cls: type[Settings], env_id: str, **overrides) -> Settings:
    """The settings of one run of ``cls.algo`` on ``env_id``: the per-env defaults with
    ``overrides`` (field=value, in the field's type or as text), checked. When the
    members change and the collected batch is not given, the batch is rounded to a
    multiple of them, near its default."""
    env_id = beacon_torch.registry.resolve_id(env_id)  # "module:env-id" registers it here
    known = {f.name: f.type for f in fields(cls)}
    unknown = set(overrides) - set(known)
    if unknown:
        raise ValueError(f"unknown {cls.algo} setting(s) {sorted(unknown)}; known: {sorted(known)}")
    values = {**defaults(cls, env_id), **{name: _typed(name, known[name], value) for name, value in overrides.items()}}
    cfg = cls(env=env_id, **{k: v for k, v in values.items() if k != "env"})
    if isinstance(cfg, Config):
        members = cfg.num_envs * cfg.collectors
        if cls.batch not in overrides and members >= 1 and getattr(cfg, cls.batch) % members:
            cfg = replace(cfg, **{cls.batch: max(members, getattr(cfg, cls.batch) // members * members)})
    if not cfg.out:
        cfg = replace(cfg, out=cls.default_out.format(algo=cls.algo, env=env_id, seed=cfg.seed))
    if isinstance(cfg, Config) and cfg.resume and (Path(cfg.out) / CHECKPOINT).is_file():
        cfg = resumed(cfg, {name: getattr(cfg, name) for name in overrides})
    return _check(cfg)


# how a run is carried out, free to change when it is resumed (with frames, the total)
RUN_OPTIONS = ("out", "resume", "progress", "logger", "checkpoint_every", "device", "collectors", "ray", "threads")


def resumed(cfg: Config, given: dict) -> Config:
    """The settings of the run saved in ``cfg.out``: a resumed run continues with the
    settings it was started with. A setting ``given`` again must match them (else a
    clear error); the run options and a new total of transitions apply, the latter said
    so."""
    saved = load_checkpoint(cfg.out)["config"]
    if saved.get("env", cfg.env) != cfg.env:
        raise ValueError(f"{cfg.out} holds a run on {saved['env']}, not {cfg.env}")
    names = {f.name for f in fields(cfg)} - {"env", "frames", *RUN_OPTIONS}
    kinds = {f.name: f.type for f in fields(cfg)}
    try:
        saved = {name: _typed(name, kinds[name], saved[name]) for name in (names | {"frames"}) & set(saved)}
    except ValueError as err:
        raise ValueError(f"resuming {Path(cfg.out) / CHECKPOINT}: {err}") from None
    for name, value in given.items():
        if name in names and name in saved and saved[name] != value:
            raise ValueError(
                f"setting '{name}' = {value!r} differs from the resumed run's {saved[name]!r}; a "
                f"resumed run keeps the settings it was started with"
            )
    frames = given.get("frames", saved.get("frames", cfg.frames))
    if frames != saved.get("frames", frames):
        print(f"resuming {cfg.out}: {saved['frames']:,} -> {frames:,} transitions")
    try:
        return _check(replace(cfg, frames=frames, **{name: saved[name] for name in names if name in saved}))
    except ValueError as err:
        raise ValueError(f"resuming {Path(cfg.out) / CHECKPOINT}: {err}") from None


def _env_of(argv: list[str] | None) -> str | None:
    """The env a command line names (before the whole line is parsed), if it is one."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--env")
    known, _ = pre.parse_known_args(argv)
    if known.env is None:
        return None
    try:
        env_id = beacon_torch.registry.resolve_id(known.env)
        env_spec(env_id)
        return env_id
    except (KeyError, ValueError, TypeError, ImportError):
        return None  # reported by the full parse


def parse(cls: type[Settings], argv: list[str] | None = None) -> Settings:
    """A run's settings from the command line: ``--env`` and any field as
    ``--name value`` (booleans as ``--name``/``--no-name``, a dict as repeated
    ``--flag NAME=VALUE``); what is not given takes the env's default. ``--help`` after
    ``--env ENV`` shows the values that env's run uses. Modules named in
    ``--env module:env-id`` are found from the working directory."""
    find_user_modules()
    env_id = _env_of(argv)
    values = {f.name: f.default for f in fields(cls) if f.default is not MISSING}
    shown_threads = "0"
    if env_id is not None:
        values.update(out=cls.default_out.format(algo=cls.algo, env=env_id, seed="SEED"))
        note = f"The defaults shown are {env_id}'s."
        try:
            count, why = threads.choose(None, env_id, values["num_envs"], training=cls.trains)
            shown_threads = f"0, which here is {count}: {why}"
        except ValueError:  # a bad $BEACON_TORCH_THREADS, refused by the full parse
            pass
    else:
        note = (
            "The defaults shown are those of an env without entries in the tables; give --env ENV with --help "
            "for ENV's."
        )
    parser = argparse.ArgumentParser(description=f"{plain(cls.__doc__)} {note}")
    try:
        values.update(defaults(cls, env_id) if env_id is not None else {})
    except ValueError as err:  # $BEACON_TORCH_COMPILE
        parser.error(str(err))
    for f in fields(cls):
        flag = "--" + f.name.replace("_", "-")
        default = values.get(f.name)
        shown = default if f.name != "out" or default else cls.default_out.format(algo="ALGO", env="ENV", seed="SEED")
        shown = shown_threads if f.name == "threads" else shown
        helptext = f"{f.metadata.get('help', '')} (default: {'none' if shown == '' else shown})"
        if getattr(cls, "in_process", False) and f.name in ("collectors", "ray"):
            helptext = argparse.SUPPRESS  # refused by a run in this process, not offered
        if f.name == "env":
            parser.add_argument(flag, required=True, help=f.metadata.get("help", ""))
        elif f.type == "dict":
            parser.add_argument(
                f.metadata["flag"], dest=f.name, action="append", metavar="NAME=VALUE", help=f.metadata.get("help", "")
            )
        elif f.type == "bool":
            parser.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=None, help=helptext)
        else:
            kind = {"int": int, "float": float, "str": str}[f.type]
            parser.add_argument(flag, dest=f.name, type=kind, default=None, metavar=f.name.upper(), help=helptext)
    args = vars(parser.parse_args(argv))
    env_id = args.pop("env")
    try:
        for f in fields(cls):
            if f.type == "dict" and args[f.name] is not None:
                args[f.name] = parse_assignments(args[f.name], f.metadata["flag"])
        return configure(cls, env_id, **{k: v for k, v in args.items() if v is not None})
    except (ValueError, KeyError, TypeError) as err:
        parser.error(str(err))


def settings_text(cfg: Settings) -> str:
    """The resolved settings of a run, one per line, as a recipe prints them at its
    start: what the run uses, whichever table, option or resumed checkpoint set it."""
    lines = [f"{cfg.algo} on {cfg.env}, settings:"]
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        if f.name == "env":
            continue
        text = f"{value:,}" if isinstance(value, int) and not isinstance(value, bool) else repr(value)
        if f.name == "frames" and isinstance(cfg, Config) and value % cfg.per_round():
            rounded = -(-value // cfg.per_round()) * cfg.per_round()
            text += f" (runs {rounded:,}: whole rounds of {cfg.per_round():,} transitions)"
        lines.append(f"  {f.name:<18} {text}")
    return "\n".join(lines)


def quiet_torchrl() -> None:
    """TorchRL's information lines (storage initialised, ...) with their colour codes
    would fill a run's log; its warnings stay."""
    logging.getLogger("torchrl").setLevel(logging.WARNING)


def script(main, cls: type[Settings], argv: list[str] | None = None) -> None:
    """A recipe run from the command line: its settings parsed, then ``main``, then (for
    a training) its learning curve drawn into ``OUT/learning_curve.png``; a bad run
    directory, a diverged training, a memory or disk too small end it with one line
    naming the problem (exit status 2), as a bad setting does."""
    cfg = parse(cls, argv)
    quiet_torchrl()
    print(settings_text(cfg), flush=True)
    count, why = threads.choose(cfg.threads or None, cfg.env, cfg.num_envs, training=cls.trains)
    print(f"  torch threads: {count} ({why})", flush=True)
    try:
        main(cfg)
        if cls.trains:
            print(learning_curve(cfg.out, progress=cfg.progress))
    except (ValueError, OSError) as err:
        print(f"{cls.algo}: error: {err}", file=sys.stderr)
        sys.exit(2)
