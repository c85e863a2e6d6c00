"""TD3 on a BEACON env with continuous actions, from TorchRL's pieces: ``TD3Loss``
(twin Q-networks, target policy smoothing, delayed actor and target updates through
``SoftUpdate``), ``AdditiveGaussianModule`` exploration, a ``Collector`` over the
batched env and a ``ReplayBuffer`` saved with each checkpoint; with ``--n-steps`` above
1, ``MultiStepTransform`` targets over that many transitions.

    python recipes/td3.py --env burgers-v0 --frames 200000
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import MultiStepTransform
from torchrl.modules import AdditiveGaussianModule
from torchrl.objectives import SoftUpdate, TD3Loss

from beacon_torch.training import networks
from beacon_torch.training.config import TD3Config, script
from beacon_torch.training.env import recipe_collector, recipe_env
from beacon_torch.training.run import Run, episode_values

ACTOR_DELAY = 2  # critic updates per actor update
ENDS = ("done", "terminated")


def n_step_transitions(transform: MultiStepTransform, data):
    """``data`` (members x time, in collection order) as transitions whose reward is the
    discounted sum over ``transform.n_steps`` steps and whose next observation is the
    one after them; ``None`` until a batch reaches past the first window. The
    transform keeps the first step's end flags, so the last step's are carried under
    other names and put back: a termination inside the window then stops the
    bootstrap, as it must."""
    for key in ENDS:
        data.set(("next", f"window_{key}"), data.get(("next", key)))
    out = transform.inv(data)
    if out is None:
        return None
    for key in ENDS:
        out.set(("next", key), out.get(("next", f"window_{key}")))
        del out["next", f"window_{key}"]
    return out


def main(cfg: TD3Config) -> dict:
    """Train TD3; returns the last logged values and the transitions collected."""
    run = Run.of(cfg)
    torch.manual_seed(cfg.seed)

    # the env, with the saved normalisation when resuming
    env = recipe_env(cfg, run.obs_norm)

    # a deterministic actor, twin critics (inside the loss) and their optimisers
    actor = networks.deterministic_actor(env, cfg.hidden).to(cfg.device)
    qvalue = networks.action_value(env, cfg.hidden).to(cfg.device)
    loss = TD3Loss(
        actor,
        qvalue,
        bounds=networks.action_bounds(env),
        policy_noise=cfg.policy_noise,
        noise_clip=cfg.noise_clip,
        loss_function="l2",
    )
    loss.make_value_estimator(gamma=cfg.gamma)
    target = SoftUpdate(loss, tau=cfg.tau)
    # Adam's fused kernel, as SAC's: its element-wise work is a tenth of an update
    actor_optim = torch.optim.Adam(
        loss.actor_network_params.flatten_keys().values(), lr=cfg.actor_lr or cfg.lr, fused=True
    )
    critic_optim = torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=cfg.lr, fused=True)

    # exploration, the replay buffer and the collector
    policy = TensorDictSequential(
        actor,
        AdditiveGaussianModule(
            spec=env.action_spec,
            sigma_init=cfg.exploration_sigma,
            sigma_end=cfg.exploration_sigma,
            annealing_num_steps=1,
        ),
    )
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(cfg.buffer_size or cfg.frames, device=cfg.device), batch_size=cfg.batch_size
    )
    # the window's tail waits for the next batch; after a resume windows start afresh
    multi_step = MultiStepTransform(cfg.n_steps, cfg.gamma) if cfg.n_steps > 1 else None
    run.restore(buffer, actor=actor, loss=loss, actor_optim=actor_optim, critic_optim=critic_optim)
    if run.remaining <= 0:
        return run.last

    # counted across a resume, so that the actor's delay keeps its phase
    updates = run.counters.get("updates", 0)

    def save() -> None:
        run.counters["updates"] = updates
        run.save(
            env,
            policy=("deterministic_actor", cfg.hidden, actor),
            buffer=buffer,
            loss=loss,
            actor_optim=actor_optim,
            critic_optim=critic_optim,
        )

    collector = recipe_collector(cfg, env, policy, run)

    for data in collector:
        values = episode_values(data)
        stored = data if multi_step is None else n_step_transitions(multi_step, data)
        if stored is not None:
            buffer.extend(stored.reshape(-1))
        # an n-step window fills only after n steps of every member
        if run.frames + data.numel() > cfg.init_random_frames and len(buffer):
            for _ in range(cfg.updates_per_batch):
                sample = buffer.sample()
                critic_loss = loss.value_loss(sample)[0]
                critic_optim.zero_grad()
                critic_loss.backward()
                critic_optim.step()
                updates += 1
                if updates % ACTOR_DELAY == 0:
                    actor_loss = loss.actor_loss(sample)[0]
                    actor_optim.zero_grad()
                    actor_loss.backward()
                    actor_optim.step()
                    target.step()
                values["loss"] = critic_loss.item()
            collector.update_policy_weights_()
        run.log(data.numel(), values, save)
    collector.shutdown()
    return run.close(save)


if __name__ == "__main__":
    script(main, TD3Config)
