"""Short-horizon actor-critic (SHAC; Xu et al., "Accelerated Policy Learning with
Parallel Differentiable Simulation", ICLR 2022): a deterministic policy trained by
backpropagating rewards through the physics, each horizon closed by a critic's value.

The batched env runs with ``differentiable=True``. Each update steps the policy through
``horizon`` actions of every member and follows the exact gradient, with respect to the
policy's weights, of the discounted rewards plus the discounted value of where the
horizon ends (of where an episode was cut short, for a member whose episode ends
inside it; nothing after a blow-up), averaged over the members and the horizon.
The value is the target critic's, differentiated through the observation into the
physics. The critic is then fitted to the TD(lambda) targets of the states the horizon
went through (TorchRL's estimator, the target critic's values), in minibatches, and the
target critic moves a share towards it. The graph is cut at the current state and the
episodes go on, ending and restarting as in any collector.

    python recipes/shac.py --env burgers-v0
    python recipes/shac.py --env cylinder-v0 --num-envs 8 --horizon 20 --grad-checkpoint

Parts of SAPO (Xing et al., "Stabilizing Reinforcement Learning in Differentiable
Multiphysics Simulation", ICLR 2025) are settings: ``--actor stochastic`` draws the
actions from a normal squashed into the action box (SAC's network, reparametrised so that
the gradient goes through the draw) and adds the entropy bonus ``-alpha log pi(a|s)`` to
each reward (in units of the mean size of the env's rewards so far), in the returns and
in the critic's targets, alpha tuned as SAC tunes it towards ``--target-entropy`` per
action dimension; ``--critics 2`` fits two critics side
by side, the horizons closed by their mean value and their targets taken from the
lowest; ``--no-target-critic`` uses the critics themselves where the slowly following
copy was; ``--optimizer adamw`` is its optimiser (betas 0.7 and 0.95); ``--layer-norm``
its hidden layers (linear, LayerNorm, SiLU) in the policy and the critics; its gradient
clipping is ``--grad-clip 0.5``. ``--lr-schedule linear`` is SHAC's own schedule (its
published configurations): the rates fall linearly to 1e-5 over the run.

``--adaptive-horizon`` adapts the horizon after each update, as AHAC (Georgiev et al.,
ICML 2024) does against a measure of the dynamics' stiffness; the measure here is how much
larger the objective's gradient is with respect to the horizon's first action than to
its last: a quarter of an octave shorter while that exceeds ``--horizon-growth``, a
quarter longer otherwise, within [``--horizon-min``, ``--horizon-max``].

``--estimator mixed`` (a stochastic policy) follows Suh et al. ("Do Differentiable
Simulators Give Better Policy Gradients?", ICML 2022): the first-order gradient and the
likelihood ratio's, each taken per group of members (``--estimator-groups``, a backward
pass through the physics each), mixed by their empirical variances, so that where the
dynamics make the first-order gradient erratic the other carries the update.

``--value-weight`` weighs the critic's closing values down in the policy's objective
(the critic is fitted as before; 0 leaves the rewards alone, as without a critic), and
``--gradient-split`` logs the policy's gradient through those values and through the
rest apart (their norms and cosine; one more backward pass an update): where the
critic's gradient, which nothing fits, outweighs the rewards' by far, the policy
follows it and not the physics.

Without the critic (``recipes/grad.py``, the same loop) each horizon's rewards are all
the policy sees: short-horizon analytic policy gradients. The policy is TD3's
deterministic actor, so ``beacon-torch eval`` and ``plot`` read these runs like any
other. ``--grad-checkpoint`` recomputes each action in the backward pass (the env's
``grad_checkpoint``), for horizons whose graph would not fit in memory.
"""

from __future__ import annotations

import copy
import math

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives.value import TDLambdaEstimator

from beacon_torch.training import networks
from beacon_torch.training.config import GradConfig, SHACConfig, script
from beacon_torch.training.env import horizon_bytes, recipe_env
from beacon_torch.training.run import Run, fits


def main(cfg: GradConfig) -> dict:
    """Train the policy on ``cfg.frames`` transitions; returns the last logged values."""
    # the graph of a horizon of every member, estimated from one action, must fit
    longest = cfg.horizon_max if cfg.adaptive_horizon else cfg.horizon
    need = horizon_bytes(
        cfg.env,
        longest,
        cfg.num_envs,
        params=cfg.params,
        grad_checkpoint=cfg.grad_checkpoint,
        kept=cfg.grad_checkpoint_after,
    )
    fits(f"the graph of {longest} differentiated actions of {cfg.num_envs} members", need, cfg.device)
    run = Run.of(cfg)
    torch.manual_seed(cfg.seed)

    # the differentiable env, with the saved normalisation when resuming
    env = recipe_env(
        cfg,
        run.obs_norm,
        differentiable=True,
        grad_checkpoint=cfg.grad_checkpoint,
        grad_checkpoint_after=cfg.grad_checkpoint_after if cfg.grad_checkpoint else 0,
    )
    base = env.base_env
    keys = networks.Keys.of(env)

    # the policy, the critic and its target; the count of updates dropped for a
    # non-finite gradient
    if cfg.actor == "stochastic":
        network = "squashed_gaussian_actor"
        actor = networks.squashed_gaussian_actor(env, cfg.hidden, normed=cfg.layer_norm)
    else:
        network = "deterministic_actor"
        actor = networks.deterministic_actor(
            env, cfg.hidden, paper_init=False, normed=cfg.layer_norm, output_scale=cfg.init_scale
        )
    network = f"normed_{network}" if cfg.layer_norm else network
    actor = actor.to(cfg.device)
    optim = optimiser(cfg, actor.parameters(), cfg.lr)
    modules = {"optim": optim}
    temperature = None
    if cfg.actor == "stochastic":
        # the entropy bonus's weight, tuned so that the policy's entropy stays near the target
        temperature = Temperature(cfg.init_alpha).to(cfg.device)
        modules.update(
            temperature=temperature, temperature_optim=optimiser(cfg, temperature.parameters(), cfg.alpha_lr)
        )
    critic = target = None
    if cfg.critic:
        # the critics' mean value closes the horizons, the lowest one their targets
        critic = networks.state_values(env, cfg.hidden, cfg.critics, normed=cfg.layer_norm).to(cfg.device)
        critic_optim = optimiser(cfg, critic.parameters(), cfg.critic_lr)
        modules.update(critic=critic, critic_optim=critic_optim)
        target = critic
        if cfg.target_critic:
            target = copy.deepcopy(critic).requires_grad_(False)
            modules["target"] = target
        targets = TDLambdaEstimator(gamma=cfg.gamma, lmbda=cfg.lmbda, value_network=networks.lowest_value(target))
        targets.set_keys(value=keys.value)
    run.restore(actor=actor, **modules)
    run.counters.setdefault("skipped", 0)
    # the actions of an update (the adaptive horizon's, kept with the checkpoint)
    steps = run.counters.setdefault("horizon", cfg.horizon)

    def save() -> None:
        run.save(env, policy=(network, cfg.hidden, actor), **modules)

    members = cfg.num_envs
    td = env.reset()
    # per member, the actions left before its first episode is cut (0: none): members
    # that all start together stay at the same instant of their episodes, and every
    # update would follow one phase of the episode at a time
    cuts = torch.randint(1, base.episode_length + 1, (members,), device=cfg.device) if cfg.stagger else None
    while run.frames < cfg.frames:
        if cfg.adaptive_horizon:
            # the last update stops at the total, not a long horizon past it
            steps = min(steps, -(-(cfg.frames - run.frames) // members))
        rollout = horizon(cfg, env, actor, target, td, cuts, temperature, steps)
        td, visited, log_probs = rollout.td, rollout.visited, rollout.log_probs
        if cfg.critic and cfg.value_weight != 1.0:
            # the closing values count for their weight only; the critic is fitted as before
            rollout.objective = rollout.objective - (1.0 - cfg.value_weight) * rollout.closing
        objective = rollout.objective
        if cfg.member_scale:
            # each member's objective in units of its own rewards' size over the horizon
            objective = objective / (rollout.sizes / steps).clamp_min(torch.finfo(objective.dtype).tiny)
        loss = (rollout.barrier - objective.sum()) / (steps * members)
        optim.zero_grad()
        split = None
        if cfg.critic and cfg.gradient_split:
            split = closing_gradient(actor, cfg.value_weight * rollout.closing.sum() / (steps * members))
        if cfg.estimator == "mixed":
            share = mix_gradients(cfg, actor, rollout, steps)
        else:
            loss.backward()
        if split is not None:
            split = gradient_split(actor, split)
        spent = steps
        if cfg.adaptive_horizon:
            growth = gradient_growth(visited)
            steps = run.counters["horizon"] = adapted(cfg, steps, growth)
        norm = torch.nn.utils.clip_grad_norm_(actor.parameters(), cfg.grad_clip)
        if cfg.lr_schedule == "linear":
            # from the transitions done, so that a resumed run goes on where it stopped
            anneal(optim, cfg.lr, run.frames / cfg.frames)
            if cfg.critic:
                anneal(critic_optim, cfg.critic_lr, run.frames / cfg.frames)
        if torch.isfinite(norm):
            optim.step()
        else:
            # a member that blew up inside the horizon can leave 0 * inf in the backward
            # pass; its episode has ended, the update is dropped
            run.counters["skipped"] += 1
        # the next update differentiates from here on: cut the graph behind the state
        base.detach_state()
        td = td.detach()
        values = {
            "reward": rollout.reward,
            "objective": -loss.item(),
            "skipped_updates": float(run.counters["skipped"]),
        }
        if torch.isfinite(norm):
            values["grad_norm"] = norm.item()
        if cfg.adaptive_horizon:
            values.update(horizon=float(spent), gradient_growth=growth)
        if cfg.estimator == "mixed":
            values["first_order_share"] = share
        if split is not None:
            # in sizes: a horizon's rewards can sum to 0
            closing = (cfg.value_weight * rollout.closing).detach().abs().sum()
            rest = (rollout.objective.detach() - cfg.value_weight * rollout.closing.detach()).abs().sum()
            values.update(split, closing_share=(closing / (closing + rest).clamp_min(1e-30)).item())
        if cfg.squash_margin:
            values["squash_barrier"] = torch.as_tensor(rollout.barrier).item() / (spent * members)
        if rollout.scores:
            values["episode_score"] = torch.cat(rollout.scores).mean().item()
        if temperature is not None:
            values.update(alpha=temperature.alpha.item(), entropy=-log_probs.mean().item())
            temperature.fit(log_probs, cfg.target_entropy * env.action_spec.shape[-1], modules["temperature_optim"])
        if cfg.critic:
            values["critic_loss"] = fit_critic(cfg, critic, target, critic_optim, targets, visited, keys)
        run.log(spent * members, values, save)
    return run.close(save)


class Rollout:
    """What a horizon leaves: the closed returns of each member (``[members]``, a graph
    back to the policy's weights), the tensordict to go on from, the transitions
    (detached, for the critic), the scores of the episodes that ended, the mean reward
    per action, the draws' log-probabilities (``[horizon, members]``, detached; empty
    for a deterministic policy) and, for the mixed estimator, the same with a graph to
    the weights only (the score function's); the squash's barrier summed over the
    horizon (0 without one), a graph to the weights; and the closing values' part of
    each member's objective (``[members]``, a graph; 0 without a critic)."""

    def __init__(
        self, objective, td, visited, scores, reward, log_probs, score_log_probs, barrier=0.0, closing=0.0, sizes=None
    ) -> None:
        self.objective, self.td, self.visited, self.scores = objective, td, visited, scores
        self.sizes = sizes
        self.reward, self.log_probs, self.score_log_probs = reward, log_probs, score_log_probs
        self.barrier, self.closing = barrier, closing


def horizon(cfg: GradConfig, env, actor, target, td, cuts=None, temperature=None, steps=None) -> Rollout:
    """One horizon of ``steps`` (None: ``cfg.horizon``) differentiated actions of every member from ``td``,
    each return closed by the ``target`` critic's value (None: no critic). With a
    ``temperature``, the actions are drawn from the stochastic policy (reparametrised, so
    that the gradient goes through the draw) and each reward has the entropy bonus
    ``-alpha s log pi(a|s)`` added (``s``: the mean size of the rewards so far), in the
    returns and in the critic's targets. A member whose
    count in ``cuts`` (None: no staggering) reaches 0 has its episode cut there, as by its length (the count
    is decremented in place; an episode cut short is not scored)."""
    keys = networks.Keys.of(env)
    steps = steps or cfg.horizon
    objective, rewards, scores, visited, log_probs, score_log_probs, barrier = 0.0, 0.0, [], [], [], [], 0.0
    closing = torch.zeros(cfg.num_envs, dtype=env.base_env.dtype, device=cfg.device)
    # per member: the sum of its rewards' sizes over the horizon
    sizes = torch.zeros_like(closing)
    # per member: the discounted rewards since the horizon or its episode began
    returns = torch.zeros(cfg.num_envs, dtype=env.base_env.dtype, device=cfg.device)
    discount = torch.ones_like(returns)
    for h in range(steps):
        # a stochastic policy draws (reparametrised), where TorchRL's default plays its mode
        with set_exploration_type(ExplorationType.RANDOM):
            td = actor(td)
        if cfg.squash_margin:
            barrier = barrier + squash_barrier(td["param"], cfg.squash_margin).sum()
        if cfg.adaptive_horizon:
            # the objective's gradient with respect to each action, read after the backward pass
            td[keys.action].retain_grad()
        if temperature is not None:
            log_prob = actor.get_dist(td).log_prob(td[keys.action])
            log_probs.append(log_prob.detach())
        if cfg.estimator == "mixed":
            # the likelihood of the same draw as a function of the weights alone
            score_log_probs.append(actor.get_dist(td.detach()).log_prob(td[keys.action].detach()))
        td, td_next = env.step_and_maybe_reset(td)
        # the default path takes no host sync for it
        cut = staggered(td, cuts) if cuts is not None else None
        if cut is not None and cut.any():
            td_next = env.reset(td_next.set("_reset", cut.unsqueeze(-1))).exclude("_reset")
        reward = td["next", "reward"][..., 0]
        rewards = rewards + reward.detach().mean()
        sizes = sizes + reward.detach().abs()
        if temperature is not None:
            reward = reward - temperature.alpha * temperature.scale(reward) * log_prob
        returns = returns + discount * reward
        discount = discount * cfg.gamma
        done = td["next", "done"][..., 0]
        last = h == steps - 1
        ends = torch.ones_like(done) if last else done
        if target is not None and (last or done.any()):
            # the value of where a return is closed: the horizon's end, or an episode
            # cut short by its length (none after a blow-up)
            value = target(td["next"].select(keys.obs))[keys.value][..., 0]
            value = torch.where(td["next", "terminated"][..., 0], 0.0, value)
            closed = returns + discount * value
            closing = closing + torch.where(ends, discount * value, 0.0)
        else:
            closed = returns
        objective = objective + torch.where(ends, closed, 0.0)
        # a member whose episode ended starts a new return
        returns = torch.where(done, 0.0, returns)
        discount = torch.where(done, 1.0, discount)
        scored = done if cut is None else done & ~cut
        if scored.any():
            scores.append(td["next", "episode_reward"][scored].detach())
        seen = td.detach()
        if temperature is not None:
            seen["next", "reward"] = reward.detach().unsqueeze(-1)
        if cfg.adaptive_horizon:
            seen.set("_action_graph", td[keys.action])
        visited.append(seen)
        td = td_next
    stacked = [torch.stack(x) if x else torch.zeros(0) for x in (log_probs, score_log_probs)]
    return Rollout(objective, td, visited, scores, float(rewards) / steps, *stacked, barrier, closing, sizes)


def squash_barrier(param: torch.Tensor, margin: float) -> torch.Tensor:
    """Per member, the quadratic barrier on the deterministic policy's pre-squash
    outputs ``param`` past ``atanh(1 - margin)``, where tanh puts an action within
    ``margin`` of the box's half-width from its edge. There tanh passes almost nothing of
    the physics' gradient back (2 % at a margin of 0.01, 0 in float32 past 9), so a
    policy that early updates pushed there stays, whatever that gradient says; the
    barrier's own gradient, however small, then dominates and brings it back to where
    the physics' gradient reaches the weights. Inside the margin it is 0."""
    excess = torch.relu(param.abs() - math.atanh(1.0 - margin))
    return excess.square().flatten(1).sum(-1)


def mix_gradients(cfg: GradConfig, actor, rollout: Rollout, steps: int) -> float:
    """Set the policy's gradient of the objective to a mix of the first-order gradient
    (through the physics) and the zeroth-order one (the likelihood ratio: each draw's
    log-probability times its member's return less the members' mean), weighted by
    their empirical variances as Suh et al. (2022) weight them: the members are split
    into ``estimator_groups`` groups, each group's two gradients are taken (a backward
    pass through the physics per group), and the first-order one gets the share
    var_0 / (var_0 + var_1) of their means. Returns that share."""
    params = [p for p in actor.parameters() if p.requires_grad]
    members = rollout.objective.shape[0]
    group = torch.arange(members, device=rollout.objective.device) % cfg.estimator_groups
    advantage = rollout.objective.detach() - rollout.objective.detach().mean()
    likelihood = rollout.score_log_probs.sum(0)  # [members]

    def flat(loss: torch.Tensor) -> torch.Tensor:
        grads = torch.autograd.grad(loss, params, retain_graph=True, allow_unused=True)
        return torch.cat(
            [(torch.zeros_like(p) if g is None else g).flatten() for p, g in zip(params, grads, strict=True)]
        )

    first, zeroth = [], []
    for k in range(cfg.estimator_groups):
        chosen = group == k
        scale = steps * int(chosen.sum())
        first.append(flat(-rollout.objective[chosen].sum() / scale))
        zeroth.append(flat(-(likelihood * advantage)[chosen].sum() / scale))
    first, zeroth = torch.stack(first), torch.stack(zeroth)
    spread = [x.var(0).sum() for x in (first, zeroth)]
    total = spread[0] + spread[1]
    share = float(spread[1] / total) if torch.isfinite(total) and total > 0 else 1.0
    mixed = share * first.mean(0) + (1.0 - share) * zeroth.mean(0)
    offset = 0
    for p in params:
        p.grad = mixed[offset : offset + p.numel()].view_as(p).clone()
        offset += p.numel()
    return share


def closing_gradient(actor, closing: torch.Tensor) -> list:
    """The policy's gradient of the loss's closing-value part ``-closing``, keeping the
    graph for the whole loss's backward pass."""
    params = [p for p in actor.parameters() if p.requires_grad]
    grads = torch.autograd.grad(-closing, params, retain_graph=True, allow_unused=True)
    return [torch.zeros_like(p) if g is None else g for p, g in zip(params, grads, strict=True)]


def gradient_split(actor, closing: list) -> dict:
    """How the policy's whole gradient (read after the backward pass, before clipping)
    splits into the part through the critic's closing values (``closing``) and the rest
    (the horizon's rewards, and the squash's barrier): their norms and the cosine of the
    angle between them."""
    total = torch.cat([p.grad.flatten() for p in actor.parameters() if p.requires_grad])
    value = torch.cat([g.flatten() for g in closing])
    rest = total - value
    norms = value.norm(), rest.norm()
    cosine = (value @ rest) / (norms[0] * norms[1]).clamp_min(torch.finfo(total.dtype).tiny)
    return {"closing_grad_norm": norms[0].item(), "reward_grad_norm": norms[1].item(), "grad_cosine": cosine.item()}


def gradient_growth(visited: list) -> float:
    """How much larger the objective's gradient is with respect to a horizon's first
    action than to its last (the mean over the members of each one's norm): how far the
    dynamics amplify what an early action does, the adaptive horizon's measure of
    stiffness (AHAC measures contact forces for it). Takes the actions' gradients out of
    the horizon's transitions."""
    norms = []
    for seen in (visited[0], visited[-1]):
        grad = seen.pop("_action_graph").grad
        norms.append(0.0 if grad is None else grad.flatten(1).norm(dim=1).mean().item())
    for seen in visited[1:-1]:
        seen.pop("_action_graph", None)
    return norms[0] / max(norms[1], 1e-30)


def adapted(cfg: SHACConfig, steps: int, growth: float) -> int:
    """The next horizon: a quarter of an octave shorter while the gradient grows over
    it by more than ``horizon_growth``, a quarter longer otherwise, within
    [``horizon_min``, ``horizon_max``]."""
    factor = 2.0**-0.25 if not growth <= cfg.horizon_growth else 2.0**0.25
    return int(min(max(round(steps * factor), cfg.horizon_min), cfg.horizon_max))


def staggered(td, cuts: torch.Tensor) -> torch.Tensor:
    """The members whose first episode is cut at this step, marked truncated and done in
    ``td["next"]`` as an episode that reached its length; counts ``cuts`` down (an
    episode that ended by itself first needs no cut)."""
    counting = cuts > 0
    cuts.sub_(counting.to(cuts.dtype))
    ended = td["next", "done"][..., 0]
    cut = counting & (cuts == 0) & ~ended
    cuts.masked_fill_(ended, 0)
    td["next", "truncated"] = td["next", "truncated"] | cut.unsqueeze(-1)
    td["next", "done"] = td["next", "done"] | cut.unsqueeze(-1)
    return cut


def fit_critic(cfg: SHACConfig, critic, target, optim, targets: TDLambdaEstimator, visited: list, keys) -> float:
    """Fit the critic to the TD(lambda) targets of the horizon's transitions (members x
    time, the target critic's values) in ``critic_minibatches`` minibatches per pass,
    ``critic_iterations`` passes; the target critic then keeps ``target_alpha`` of itself.
    Returns the last pass's mean squared error."""
    batch = torch.stack(visited, -1)  # [members, horizon]: time last, as TorchRL's estimators read it
    with torch.no_grad():
        goal = targets.value_estimate(batch)
    observations = batch[keys.obs].reshape(-1, batch[keys.obs].shape[-1])
    goal = goal.reshape(-1)
    size = goal.numel()
    for _ in range(cfg.critic_iterations):
        order = torch.randperm(size, device=goal.device)
        total = 0.0
        for chunk in order.chunk(cfg.critic_minibatches):
            # each critic its own squared error
            predicted = networks.each_value(critic, observations[chunk])[..., 0]
            loss = (predicted - goal[chunk]).pow(2).mean(-1).sum()
            optim.zero_grad()
            loss.backward()
            optim.step()
            total += loss.item() / cfg.critics * chunk.numel()
    if target is not critic:
        with torch.no_grad():
            for kept, new in zip(target.parameters(), critic.parameters(), strict=True):
                kept.lerp_(new, 1.0 - cfg.target_alpha)
    return total / size


class Temperature(torch.nn.Module):
    """The weight alpha of the entropy bonus, as its logarithm, fitted as SAC's is: down
    while the policy's entropy is above the target, up while below. The bonus is counted
    in the env's own units of reward (:meth:`scale`): the rewards of these envs range
    from thousandths (burgers) to hundreds (the cavities) per action."""

    def __init__(self, alpha: float) -> None:
        super().__init__()
        self.log_alpha = torch.nn.Parameter(torch.tensor(math.log(alpha)))
        self.register_buffer("seen", torch.zeros(2, dtype=torch.float64))  # sum of |reward|, count

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp().detach()

    def scale(self, reward: torch.Tensor) -> torch.Tensor:
        """The mean size of every reward seen so far, ``reward`` (one action's) included."""
        self.seen[0] += reward.detach().abs().sum().double()
        self.seen[1] += reward.numel()
        return (self.seen[0] / self.seen[1]).to(reward.dtype).clamp_min(torch.finfo(reward.dtype).tiny)

    def fit(self, log_probs: torch.Tensor, target: float, optim: torch.optim.Optimizer) -> None:
        loss = -(self.log_alpha * (log_probs + target)).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()


def anneal(optim: torch.optim.Optimizer, lr: float, done: float, last: float = 1e-5) -> None:
    """The linear schedule's rate after the share ``done`` of the run: ``lr`` down to
    ``last``."""
    for group in optim.param_groups:
        group["lr"] = lr + (last - lr) * min(done, 1.0)


def optimiser(cfg: GradConfig, parameters, lr: float) -> torch.optim.Optimizer:
    """Adam, or AdamW with SAPO's moments (betas 0.7 and 0.95) and torch's weight decay."""
    if cfg.optimizer == "adamw":
        return torch.optim.AdamW(parameters, lr=lr, betas=(0.7, 0.95))
    return torch.optim.Adam(parameters, lr=lr)


if __name__ == "__main__":
    script(main, SHACConfig)
