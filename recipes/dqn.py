"""DQN on a BEACON env with discrete actions (lorenz-v0, mixing-v0), from TorchRL's
pieces: ``DQNLoss`` (plain DQN as the paper's agent: the target network's maximum, a
hard copy into it every ``target_every`` updates through ``HardUpdate``), a
``QValueActor``, epsilon-greedy exploration (``EGreedyModule``), a ``Collector`` over
the batched env and a ``ReplayBuffer`` saved with each checkpoint.

    python recipes/dqn.py --env lorenz-v0 --frames 200000
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.modules import EGreedyModule
from torchrl.objectives import DQNLoss, HardUpdate

from beacon_torch.training import networks
from beacon_torch.training.config import DQNConfig, script
from beacon_torch.training.env import recipe_collector, recipe_env
from beacon_torch.training.run import Run, episode_values


def main(cfg: DQNConfig) -> dict:
    """Train DQN; returns the last logged values and the transitions collected."""
    run = Run.of(cfg)
    torch.manual_seed(cfg.seed)

    # the env, with the saved normalisation when resuming
    env = recipe_env(cfg, run.obs_norm)

    # the action values (the greedy policy), the DQN loss with its target network
    qvalue = networks.qvalue_actor(env, cfg.hidden).to(cfg.device)
    loss = DQNLoss(qvalue, delay_value=True, double_dqn=False, action_space="categorical")
    loss.make_value_estimator(gamma=cfg.gamma)
    target = HardUpdate(loss, value_network_update_interval=cfg.target_every)
    target.counter = run.counters.get("target_counter", 0)  # a resume keeps the copies' schedule
    optim = torch.optim.Adam(loss.parameters(), lr=cfg.lr)

    # epsilon-greedy exploration, annealed over the transitions; the replay buffer
    explore = EGreedyModule(
        spec=env.action_spec, eps_init=cfg.eps_init, eps_end=cfg.eps_end, annealing_num_steps=cfg.eps_frames
    )
    explore.step(run.frames)
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(cfg.buffer_size or cfg.frames, device=cfg.device), batch_size=cfg.batch_size
    )
    run.restore(buffer, actor=qvalue, loss=loss, optim=optim)
    if run.remaining <= 0:
        return run.last

    def save() -> None:
        run.counters["target_counter"] = target.counter
        run.save(env, policy=("qvalue_actor", cfg.hidden, qvalue), buffer=buffer, loss=loss, optim=optim)

    collector = recipe_collector(cfg, env, TensorDictSequential(qvalue, explore), run)

    for data in collector:
        buffer.extend(data.reshape(-1))
        values = episode_values(data)
        if run.frames + data.numel() > cfg.init_random_frames:
            for _ in range(cfg.updates_per_batch):
                value_loss = loss(buffer.sample())["loss"]
                optim.zero_grad()
                value_loss.backward()
                optim.step()
                target.step()
            values["loss"] = value_loss.item()
            collector.update_policy_weights_()
        explore.step(data.numel())
        run.log(data.numel(), values, save)
    collector.shutdown()
    return run.close(save)


if __name__ == "__main__":
    script(main, DQNConfig)
