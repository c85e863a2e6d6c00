"""PPO on a BEACON env, from TorchRL's pieces: ``ClipPPOLoss`` with ``GAE``, a
``Collector`` over the batched env, a replay buffer for the minibatches, observation
normalisation (``ObservationNorm``) and episode returns (``RewardSum``) as transforms,
and a ``CSVLogger``. The paper's settings are the defaults (``recipes/config.py``).

    beacon-torch train lorenz-v0 --algo ppo --frames 200000 --out runs/ppo-lorenz

A run directory holds ``checkpoint.pt`` (networks, optimiser, normalisation, frames
collected; written every ``checkpoint_every`` updates and at the end) and the logger's
CSV files; ``train(..., resume=True)`` continues from the checkpoint.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers.samplers import SamplerWithoutReplacement
from torchrl.envs import Compose, ObservationNorm, RewardSum, TransformedEnv
from torchrl.modules import ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE
from torchrl.record.loggers import CSVLogger

import beacon_torch
from beacon_torch.recipes.config import PPOConfig

NORM_STEPS = 16  # random steps that set the observation normalisation


def make_env(env_id: str, cfg: PPOConfig, *, device="cpu", seed: int = 0, norm: dict | None = None, **env_kwargs) -> TransformedEnv:
    """The batched env with observation normalisation and episode returns; ``norm`` (a
    saved ``ObservationNorm`` state) instead of statistics from a random rollout."""
    base = beacon_torch.make(env_id, cfg.num_envs, device=device, seed=seed, **env_kwargs)
    if isinstance(base.observation_key, tuple):
        raise ValueError(f"{env_id}: the PPO recipe handles single-agent envs; multi-agent layouts are not supported yet")
    loc, scale = (norm["loc"], norm["scale"]) if norm is not None else (None, None)
    env = TransformedEnv(base, Compose(ObservationNorm(loc=loc, scale=scale, in_keys=["observation"], standard_normal=True), RewardSum()))
    if norm is None:
        env.transform[0].init_stats(num_iter=NORM_STEPS, reduce_dim=(0, 1), cat_dim=1)
    return env


def _orthogonal(module: nn.Module, gain: float = 2**0.5) -> nn.Module:
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.orthogonal_(layer.weight, gain)
            nn.init.zeros_(layer.bias)
    return module


def make_actor(env: TransformedEnv, hidden: int) -> ProbabilisticActor:
    """The paper's actor: a shared tanh layer, then one tanh head each for the mean and
    the spread (continuous) or for the logits (discrete)."""
    n_obs = env.observation_spec["observation"].shape[-1]
    spec = env.action_spec
    trunk = [nn.Linear(n_obs, hidden), nn.Tanh()]
    if env.base_env.discrete:
        net = _orthogonal(nn.Sequential(*trunk, nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, env.base_env.n_actions)))
        module = TensorDictModule(net, in_keys=["observation"], out_keys=["logits"])
        return ProbabilisticActor(module, in_keys=["logits"], distribution_class=torch.distributions.Categorical, return_log_prob=True, spec=spec)
    n_act = spec.shape[-1]

    class Heads(nn.Module):
        def __init__(self):
            super().__init__()
            self.trunk = nn.Sequential(*trunk)
            self.mean = nn.Sequential(nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, n_act))
            self.spread = nn.Sequential(nn.Linear(hidden, hidden), nn.Tanh(), nn.Linear(hidden, n_act))
            self.scale = NormalParamExtractor()

        def forward(self, obs):
            z = self.trunk(obs)
            return self.scale(torch.cat((self.mean(z), self.spread(z)), -1))

    module = TensorDictModule(_orthogonal(Heads()), in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
        return_log_prob=True,
        spec=spec,
    )


def make_critic(env: TransformedEnv, hidden: int) -> ValueOperator:
    n_obs = env.observation_spec["observation"].shape[-1]
    net = _orthogonal(nn.Sequential(nn.Linear(n_obs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, 1)))
    return ValueOperator(net, in_keys=["observation"])


def train(env_id: str, cfg: PPOConfig, out: str | Path, *, seed: int = 0, device="cpu", resume: bool = False, checkpoint_every: int = 10, progress: bool = True) -> dict:
    """Train PPO; returns the last logged values and the frames collected."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    state = None
    if resume:
        if not ckpt_path.is_file():
            raise FileNotFoundError(f"no checkpoint to resume in {out}")
        state = torch.load(ckpt_path, weights_only=False)
        if state["env"] != env_id or state["algo"] != "ppo":
            raise ValueError(f"{out} holds a {state['algo']} run on {state['env']}, not ppo on {env_id}")
    torch.manual_seed(seed)
    env = make_env(env_id, cfg, device=device, seed=seed, norm=state["obs_norm"] if state else None)
    actor, critic = make_actor(env, cfg.hidden).to(device), make_critic(env, cfg.hidden).to(device)
    loss = ClipPPOLoss(actor, critic, clip_epsilon=cfg.clip, entropy_coeff=cfg.entropy, normalize_advantage=True, loss_critic_type="l2")
    advantage = GAE(gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False)
    optim = torch.optim.Adam([{"params": actor.parameters(), "lr": cfg.actor_lr}, {"params": critic.parameters(), "lr": cfg.critic_lr}])
    frames = 0
    if state is not None:
        actor.load_state_dict(state["actor"])
        critic.load_state_dict(state["critic"])
        optim.load_state_dict(state["optim"])
        frames = state["frames"]
    remaining = cfg.frames - frames
    logger = CSVLogger(exp_name="ppo", log_dir=str(out))
    last: dict = {"frames": frames}
    if remaining <= 0:
        return last

    def save() -> None:
        torch.save(
            {
                "env": env_id,
                "algo": "ppo",
                "seed": seed,
                "config": asdict(cfg),
                "frames": frames,
                "actor": actor.state_dict(),
                "critic": critic.state_dict(),
                "optim": optim.state_dict(),
                "obs_norm": env.transform[0].state_dict(),
            },
            ckpt_path,
        )

    collector = Collector(env, actor, frames_per_batch=cfg.n_rollout, total_frames=remaining, device=device, auto_register_policy_transforms=False)
    buffer = ReplayBuffer(storage=LazyTensorStorage(cfg.n_rollout, device=device), sampler=SamplerWithoutReplacement(), batch_size=cfg.n_rollout // cfg.minibatches)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=cfg.frames, initial=frames, unit="frames", desc=f"ppo {env_id}")
    for update, data in enumerate(collector):
        with torch.no_grad():
            data = advantage(data)
        buffer.extend(data.reshape(-1))
        for _ in range(cfg.epochs):
            for _ in range(cfg.minibatches):
                losses = loss(buffer.sample())
                total = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
                optim.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), cfg.grad_clip)
                optim.step()
        collector.update_policy_weights_()
        frames += data.numel()
        done = data["next", "done"][..., 0]
        last = {"frames": frames, "reward": data["next", "reward"].mean().item(), "loss": total.item()}
        if done.any():
            last["episode_score"] = data["next", "episode_reward"][..., 0][done].mean().item()
        for name, value in last.items():
            if name != "frames":
                logger.log_scalar(name, value, step=frames)
        if bar is not None:
            bar.update(data.numel())
            bar.set_postfix({k: f"{v:.4g}" for k, v in last.items() if k != "frames"})
        if (update + 1) % checkpoint_every == 0:
            save()
    collector.shutdown()
    if bar is not None:
        bar.close()
    save()
    return last
