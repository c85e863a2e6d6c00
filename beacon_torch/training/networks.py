"""The paper's networks, built for a training env (``env.make_env``), initialised as
the paper's agents were: hidden layers orthogonal with gain 1 and zero biases, every
output layer zero (weights and biases), so that a new continuous policy has mean 0 and
standard deviation 0.5 everywhere, a new discrete one is uniform, and values start at 0.

A checkpoint records the network of its policy by name (``NETWORKS``) with its width,
so that evaluation rebuilds any trained policy without knowing the algorithm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import torch
from tensordict import NestedKey
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import TransformedEnv
from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor, QValueActor, TanhModule, ValueOperator

from beacon_torch.training.env import sibling


def initialised(module: nn.Module, *outputs: nn.Linear) -> nn.Module:
    """``module`` with its linear layers orthogonal (gain 1, zero biases) and the
    ``outputs`` zero."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, 1.0)
            nn.init.zeros_(layer.bias)
    for layer in outputs:
        nn.init.zeros_(layer.weight)
        nn.init.zeros_(layer.bias)
    return module


def last_linear(module: nn.Module) -> nn.Linear:
    return [layer for layer in module.modules() if isinstance(layer, nn.Linear)][-1]


@dataclass(frozen=True)
class Keys:
    """Where a policy reads and writes: at the root, or under ``"agents"`` in a
    multi-agent layout (shkadov-separable-v0), where one policy and one critic are
    shared by the agents (the agent dimension is one more batch dimension to the
    networks) and each agent's advantage comes from its own reward."""

    obs: NestedKey
    action: NestedKey
    reward: NestedKey
    log_prob: NestedKey
    value: NestedKey
    advantage: NestedKey
    value_target: NestedKey
    done: NestedKey
    terminated: NestedKey

    @classmethod
    def of(cls, env: TransformedEnv) -> Keys:
        base = env.base_env
        at = partial(sibling, base.observation_key)
        names = ("action_log_prob", "state_value", "advantage", "value_target", "done", "terminated")
        return cls(base.observation_key, base.action_key, base.reward_key, *map(at, names))

    @property
    def agents(self) -> bool:
        return isinstance(self.obs, tuple)


class Heads(nn.Module):
    """The paper's continuous actor: a shared tanh layer, then a mean head ending in tanh
    (within the action box) and a spread head ending in a sigmoid (0 to 1), the
    parameters of a normal distribution. Module level, so that multi-process collectors
    can pickle it."""

    def __init__(self, n_obs: int, hidden: int, n_act: int) -> None:
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(n_obs, hidden), nn.Tanh())
        self.mean = nn.Sequential(nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, n_act), nn.Tanh())
        self.spread = nn.Sequential(nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, n_act), nn.Sigmoid())

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z = self.trunk(obs)
        return self.mean(z), self.spread(z)


def n_observations(env: TransformedEnv) -> int:
    return env.observation_spec[env.base_env.observation_key].shape[-1]


def stochastic_actor(env: TransformedEnv, hidden: int) -> ProbabilisticActor:
    """The paper's PPO actor: a shared tanh layer, then one tanh head each for the mean
    and the spread of a normal distribution (continuous actions) or the logits of a
    categorical one (discrete actions)."""
    keys = Keys.of(env)
    n_obs = n_observations(env)
    if env.base_env.discrete:
        trunk = [nn.Linear(n_obs, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh()]
        net = nn.Sequential(*trunk, nn.Linear(hidden, env.base_env.n_actions))
        net = initialised(net, last_linear(net))
        module = TensorDictModule(net, in_keys=[keys.obs], out_keys=["logits"])
        return ProbabilisticActor(
            module,
            in_keys=["logits"],
            distribution_class=torch.distributions.Categorical,
            return_log_prob=True,
            spec=env.action_spec,
        )
    heads = Heads(n_obs, hidden, env.full_action_spec[keys.action].shape[-1])
    return normal_actor(env, initialised(heads, last_linear(heads.mean), last_linear(heads.spread)))


def normal_actor(env: TransformedEnv, heads: nn.Module) -> ProbabilisticActor:
    """The policy drawing from the diagonal normal whose mean and spread ``heads`` give:
    as the paper's agent, a normal sample, clipped to the box by the env's transform
    (env.make_env) while the loss sees the sample itself; not a tanh-squashed
    distribution, whose vanishing gradient at the bounds traps "no control" policies."""
    keys = Keys.of(env)
    params = [sibling(keys.action, "loc"), sibling(keys.action, "scale")]
    return ProbabilisticActor(
        TensorDictModule(heads, in_keys=[keys.obs], out_keys=params),
        in_keys=dict(zip(("loc", "scale"), params, strict=True)),
        out_keys=[keys.action],
        log_prob_key=keys.log_prob,
        distribution_class=IndependentNormal,
        return_log_prob=True,
        spec=env.full_action_spec,
    )


def sb3_initialised(net: nn.Sequential, out_gain: float) -> nn.Sequential:
    """``net`` initialised as Stable-Baselines3 does: orthogonal with gain sqrt(2), zero
    biases, the last layer with gain ``out_gain``."""
    for layer in net:
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, math.sqrt(2.0))
            nn.init.zeros_(layer.bias)
    nn.init.orthogonal_(net[-1].weight, out_gain)
    return net


class FreeSpread(nn.Module):
    """Stable-Baselines3's continuous actor (its ``MlpPolicy``): two tanh layers to an
    unbounded mean, and one learned log-spread per action dimension, the same in every
    state, starting at 0 (a spread of 1)."""

    def __init__(self, n_obs: int, hidden: int, n_act: int) -> None:
        super().__init__()
        self.mean = nn.Sequential(
            nn.Linear(n_obs, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, n_act)
        )
        self.log_spread = nn.Parameter(torch.zeros(n_act))
        # 0.01 at the mean, so that the first actions are the spread's draws about 0
        sb3_initialised(self.mean, 0.01)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = self.mean(obs)
        return loc, self.log_spread.exp().expand_as(loc)


def sb3_critic(n_obs: int, hidden: int) -> nn.Sequential:
    """Stable-Baselines3's PPO critic (its ``MlpPolicy``): two tanh layers, the value's
    layer with gain 1."""
    net = nn.Sequential(nn.Linear(n_obs, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, 1))
    return sb3_initialised(net, 1.0)


def free_spread_actor(env: TransformedEnv, hidden: int) -> ProbabilisticActor:
    """PPO's actor as Stable-Baselines3 builds it (:class:`FreeSpread`), drawing as the
    paper's does (:func:`normal_actor`)."""
    if env.base_env.discrete:
        raise ValueError(f"{env.base_env.env_id}: the free-spread actor is for continuous actions")
    n_act = env.full_action_spec[Keys.of(env).action].shape[-1]
    return normal_actor(env, FreeSpread(n_observations(env), hidden, n_act))


def normed_mlp(n_in: int, n_out: int, hidden: int) -> MLP:
    """Two hidden layers of SAPO's kind: linear, LayerNorm, SiLU."""
    return MLP(
        in_features=n_in,
        out_features=n_out,
        num_cells=[hidden, hidden],
        activation_class=nn.SiLU,
        norm_class=nn.LayerNorm,
        norm_kwargs={"normalized_shape": hidden},
    )


def state_value(env: TransformedEnv, hidden: int, normed: bool = False, kind: str = "paper") -> ValueOperator:
    """The paper's PPO critic: two ReLU layers (``normed``: :func:`normed_mlp`'s;
    ``kind="sb3"``: :func:`sb3_critic`)."""
    keys = Keys.of(env)
    if kind == "sb3":
        return ValueOperator(sb3_critic(n_observations(env), hidden), in_keys=[keys.obs], out_keys=[keys.value])
    if normed:
        net = normed_mlp(n_observations(env), 1, hidden)
    else:
        net = nn.Sequential(
            nn.Linear(n_observations(env), hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, 1),
        )
    return ValueOperator(initialised(net, last_linear(net)), in_keys=[keys.obs], out_keys=[keys.value])


class Ensemble(nn.Module):
    """Networks of the same input side by side (SAPO's twin critics): their mean output,
    or with ``lowest`` their lowest; :meth:`each` stacks every one's output first."""

    def __init__(self, nets: list[nn.Module], lowest: bool = False) -> None:
        super().__init__()
        self.nets = nn.ModuleList(nets)
        self.lowest = lowest

    def each(self, x: torch.Tensor) -> torch.Tensor:
        return torch.stack([net(x) for net in self.nets])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        values = self.each(x)
        return values.amin(0) if self.lowest else values.mean(0)


def state_values(env: TransformedEnv, hidden: int, count: int, normed: bool = False) -> ValueOperator:
    """``count`` critics of :func:`state_value`'s kind giving their mean value (one:
    that critic itself)."""
    if count == 1:
        return state_value(env, hidden, normed)
    nets = [state_value(env, hidden, normed).module for _ in range(count)]
    return ValueOperator(Ensemble(nets), in_keys=[Keys.of(env).obs], out_keys=[Keys.of(env).value])


def lowest_value(critics: ValueOperator) -> ValueOperator:
    """The same critics (shared, not copied) giving the lowest of their values."""
    if not isinstance(critics.module, Ensemble):
        return critics
    return ValueOperator(
        Ensemble(list(critics.module.nets), lowest=True), in_keys=critics.in_keys, out_keys=critics.out_keys
    )


def each_value(critics: ValueOperator, obs: torch.Tensor) -> torch.Tensor:
    """Every critic's value of ``obs``, stacked first (``[critics, ..., 1]``)."""
    if isinstance(critics.module, Ensemble):
        return critics.module.each(obs)
    return critics.module(obs).unsqueeze(0)


def action_bounds(env: TransformedEnv) -> tuple[torch.Tensor, torch.Tensor]:
    """The action box of one member (the env's spec carries the batch dimension), or of
    one agent (the same for each)."""
    spec = env.full_action_spec[Keys.of(env).action]
    space, n_act = spec.space, spec.shape[-1]
    return space.low.reshape(-1, n_act)[0], space.high.reshape(-1, n_act)[0]


def deterministic_actor(
    env: TransformedEnv, hidden: int, paper_init: bool = True, normed: bool = False, output_scale: float = 1.0
) -> TensorDictSequential:
    """A deterministic policy (TD3, gradient-based control): an MLP squashed into the
    action box. ``paper_init`` False keeps torch's default initialisation (gradient-based
    control, whose first updates need a gradient through every layer), its output layer
    times ``output_scale`` (near 0: a policy near no control, still with a gradient
    through every layer); ``normed``: the hidden layers of :func:`normed_mlp`."""
    low, high = action_bounds(env)
    if normed:
        net = normed_mlp(n_observations(env), env.action_spec.shape[-1], hidden)
    else:
        net = MLP(
            in_features=n_observations(env),
            out_features=env.action_spec.shape[-1],
            num_cells=[hidden, hidden],
            activation_class=nn.ReLU,
        )
    if paper_init:
        initialised(net, last_linear(net))
    with torch.no_grad():
        for tensor in last_linear(net).parameters():
            tensor.mul_(output_scale)
    return TensorDictSequential(
        TensorDictModule(net, in_keys=["observation"], out_keys=["param"]),
        TanhModule(in_keys=["param"], out_keys=["action"], low=low, high=high),
    )


def squashed_gaussian_actor(env: TransformedEnv, hidden: int, normed: bool = False) -> ProbabilisticActor:
    """SAC's actor: an MLP giving the location and scale of a normal distribution
    squashed by tanh into the action box (deterministic: the squashed location);
    ``normed``: the hidden layers of :func:`normed_mlp`. In a multi-agent layout one
    actor is shared by the agents (:class:`Keys`)."""
    from tensordict.nn.distributions import NormalParamExtractor
    from torchrl.modules import TanhNormal

    keys = Keys.of(env)
    low, high = action_bounds(env)
    n_act = env.full_action_spec[keys.action].shape[-1]
    if normed:
        net = normed_mlp(n_observations(env), 2 * n_act, hidden)
    else:
        net = MLP(
            in_features=n_observations(env),
            out_features=2 * n_act,
            num_cells=[hidden, hidden],
            activation_class=nn.ReLU,
        )
    params = [sibling(keys.action, "loc"), sibling(keys.action, "scale")]
    module = TensorDictModule(nn.Sequential(net, NormalParamExtractor()), in_keys=[keys.obs], out_keys=params)
    return ProbabilisticActor(
        module,
        in_keys=dict(zip(("loc", "scale"), params, strict=True)),
        out_keys=[keys.action],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": low, "high": high},
        return_log_prob=False,
        spec=env.full_action_spec,
    )


class PairMLP(MLP):
    """TorchRL's MLP of an (observation, action) pair, its first layer applied to the
    two parts apart rather than to their concatenation: the same parameters, the same
    values, but the actor's loss, which differentiates the value in the action only, no
    longer pays for the gradient of the observation's part. Where observations are
    wide (rbc2d's 1,408 to 1,536 sensors) that gradient was a sixth of an update."""

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        first, *rest = self
        n = obs.shape[-1]
        out = nn.functional.linear(obs, first.weight[:, :n], first.bias)
        out = out + nn.functional.linear(action, first.weight[:, n:])
        for layer in rest:
            out = layer(out)
        return out


def action_value(env: TransformedEnv, hidden: int) -> ValueOperator:
    """TD3's and SAC's critic: the value of an (observation, action) pair; shared by
    the agents in a multi-agent layout."""
    keys = Keys.of(env)
    n_in = n_observations(env) + env.full_action_spec[keys.action].shape[-1]
    net = PairMLP(in_features=n_in, out_features=1, num_cells=[hidden, hidden], activation_class=nn.ReLU)
    return ValueOperator(
        initialised(net, last_linear(net)),
        in_keys=[keys.obs, keys.action],
        out_keys=[sibling(keys.obs, "state_action_value")],
    )


def qvalue_actor(env: TransformedEnv, hidden: int) -> QValueActor:
    """DQN's policy: the values of every discrete action; the greedy one is played."""
    net = MLP(
        in_features=n_observations(env),
        out_features=env.base_env.n_actions,
        num_cells=[hidden, hidden],
        activation_class=nn.ReLU,
    )
    return QValueActor(initialised(net, last_linear(net)), in_keys=["observation"], action_space="categorical")


# the policies a checkpoint can hold, by the name it records
NETWORKS = {
    "stochastic_actor": stochastic_actor,
    "free_spread_actor": free_spread_actor,
    "deterministic_actor": deterministic_actor,
    "squashed_gaussian_actor": squashed_gaussian_actor,
    "qvalue_actor": qvalue_actor,
    # the same with SAPO's hidden layers (the actor-critic's --layer-norm)
    "normed_deterministic_actor": partial(deterministic_actor, paper_init=False, normed=True),
    "normed_squashed_gaussian_actor": partial(squashed_gaussian_actor, normed=True),
}


def policy(env: TransformedEnv, network: str, hidden: int) -> TensorDictModule:
    """The policy network ``network`` (a name of ``NETWORKS``) of width ``hidden``."""
    if network not in NETWORKS:
        raise ValueError(f"unknown policy network {network!r}; known: {sorted(NETWORKS)}")
    return NETWORKS[network](env, hidden)
