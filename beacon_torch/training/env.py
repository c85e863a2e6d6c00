"""The training env: a batched BEACON env with observation normalisation, episode
returns and action clipping as TorchRL transforms, and the collectors that step it."""

from __future__ import annotations

from functools import partial
from importlib.util import find_spec

import torch
from torchrl.envs import ClipTransform, Compose, ObservationNorm, RewardSum, TransformedEnv

import beacon_torch
from beacon_torch import seeds
from beacon_torch.autograd import saved_storages
from beacon_torch.registry import qualified_id

# random steps whose observations set the normalisation: 64 reach past the start-up of
# every env (burgers' sensors see the inlet noise only after about 40 actions; with 16
# steps their scale was 1e-5 and normalised observations reached 1e5)
NORM_STEPS = 64


def sibling(key: str | tuple[str, ...], name: str) -> str | tuple[str, ...]:
    """The entry ``name`` next to ``key``: ``("agents", "reward")`` -> ``("agents", name)``."""
    return (*key[:-1], name) if isinstance(key, tuple) else name


def make_env(
    env_id: str,
    num_envs: int,
    *,
    device="cpu",
    seed: int = 0,
    norm: dict | None = None,
    norm_steps: int = NORM_STEPS,
    **env_kwargs,
) -> TransformedEnv:
    """The batched env with observation normalisation and episode returns; the
    statistics come from ``norm`` (a saved ``ObservationNorm`` state) or else from a
    rollout of ``norm_steps`` random actions (0: none, the identity, the raw
    observations that the paper's agents saw). In a multi-agent layout
    (shkadov-separable-v0) the statistics are shared by the agents, as the policy is,
    and the episode returns are per agent, next to their rewards. Continuous actions
    reach the env clipped to its box."""
    base = beacon_torch.make(env_id, num_envs, device=device, seed=seed, **env_kwargs)
    obs, reward = base.observation_key, base.reward_key
    if norm is None and norm_steps == 0:
        n_obs = base.observation_spec[obs].shape[-1]
        norm = {
            "loc": torch.zeros(n_obs, dtype=base.dtype, device=device),
            "scale": torch.ones(n_obs, dtype=base.dtype, device=device),
        }
    loc, scale = (None, None)
    if norm is not None:
        # in the env's dtype and place, checked after the cast (a float64 scale of
        # 1e-300 is zero in float32)
        loc, scale = (norm[k].to(device=base.device, dtype=base.dtype) for k in ("loc", "scale"))
        if not (bool(torch.isfinite(loc).all()) and bool(torch.isfinite(scale).all()) and bool((scale > 0).all())):
            raise ValueError(
                f"{env_id}: the observation statistics are not finite with a positive scale in {base.dtype}"
            )
    transforms = [
        ObservationNorm(loc=loc, scale=scale, in_keys=[obs], standard_normal=True),
        RewardSum(in_keys=[reward], out_keys=[sibling(reward, "episode_reward")]),
    ]
    if not base.discrete:
        # a policy's sample may leave the box: the env gets it clipped, the data keeps it
        low, high = (
            base.full_action_spec[base.action_key].space.low.unique(),
            base.full_action_spec[base.action_key].space.high.unique(),
        )
        transforms.append(ClipTransform(in_keys_inv=[base.action_key], low=low.item(), high=high.item()))
    env = TransformedEnv(base, Compose(*transforms))
    if norm is None:
        agent_dims = base.observation_spec[obs].ndim - base.batch_dims - 1
        env.transform[0].init_stats(num_iter=norm_steps, reduce_dim=tuple(range(2 + agent_dims)), cat_dim=1)
    return env


def recipe_env(cfg, norm: dict | None, **options) -> TransformedEnv:
    """A recipe's training env from its settings ``cfg``: :func:`make_env` with the
    run's saved normalisation ``norm`` (None: measured anew) and ``options`` of the
    env (``differentiable=True``, ...)."""
    return make_env(
        cfg.env,
        cfg.num_envs,
        device=cfg.device,
        seed=cfg.seed,
        norm=norm,
        norm_steps=cfg.norm_steps,
        compile=cfg.compile,
        params=cfg.params,
        starts=cfg.starts or None,
        **options,
    )


def recipe_collector(cfg, env: TransformedEnv, policy, run, frames_per_batch: int | None = None):
    """A recipe's collector from its settings ``cfg``: :func:`make_collector` over its
    training ``env`` for the transitions ``run`` has left, with the random actions of
    ``cfg.init_random_frames`` (off-policy recipes) that a resumed run has not yet taken,
    ``frames_per_batch`` a batch (``cfg.frames_per_batch`` unless given)."""
    return make_collector(
        cfg.env,
        env,
        policy,
        frames_per_batch=cfg.frames_per_batch if frames_per_batch is None else frames_per_batch,
        total_frames=run.remaining,
        init_random_frames=max(0, getattr(cfg, "init_random_frames", 0) - run.frames),
        collectors=cfg.collectors,
        ray=cfg.ray or None,
        seed=cfg.seed,
        device=cfg.device,
        params=cfg.params,
    )


def make_collector(
    env_id: str,
    env: TransformedEnv,
    policy,
    *,
    frames_per_batch: int,
    total_frames: int,
    collectors: int = 1,
    ray: str | None = None,
    seed: int = 0,
    device="cpu",
    init_random_frames: int = 0,
    params: dict | None = None,
):
    """A TorchRL collector over the batched ``env``: a ``Collector`` in this process;
    with ``collectors`` > 1 a ``MultiSyncCollector`` of that many processes; with
    ``ray`` (a Ray cluster address, or "local" for a Ray instance on this machine) a
    synchronous ``RayCollector`` of ``collectors`` Ray actors. Each remote collector
    steps its own batched env of the same size and physical ``params`` (seeded apart,
    with ``env``'s observation normalisation), and their batches are stacked into one ``[collectors, members,
    time]`` batch."""
    from torchrl.collectors import Collector, MultiSyncCollector

    if collectors < 1:
        raise ValueError(f"collectors must be a positive integer, got {collectors}")
    kwargs = dict(frames_per_batch=frames_per_batch, total_frames=total_frames, init_random_frames=init_random_frames)
    local = dict(device=device, auto_register_policy_transforms=False)
    if collectors == 1 and ray is None:
        return Collector(env, policy, **kwargs, **local)
    members = env.batch_size.numel()
    if frames_per_batch % (collectors * members):
        raise ValueError(
            f"the collected batch ({frames_per_batch}) must be a multiple of collectors x members "
            f"({collectors} x {members})"
        )
    base = env.base_env
    makers = [
        partial(
            make_env,
            qualified_id(env_id),  # a worker process imports what registered it
            members,
            device=device,
            seed=seeds.worker(seed, k),
            norm=env.transform[0].state_dict(),
            dtype=base.dtype,
            compile=base.physics.kernels.options or False,
            starts=base.starts,
            **(params or {}),
        )
        for k in range(collectors)
    ]
    if ray is None:
        return MultiSyncCollector(makers, policy, cat_results="stack", **kwargs, **local)
    if find_spec("ray") is None:
        raise ValueError("collection on Ray needs the ray package (pip install 'beacon-torch[ray]')")
    import ray as ray_lib
    from torchrl.collectors.distributed import RayCollector

    init = ray_init_config(ray, collectors)
    ray_lib.init(**init)
    check_ray_fits(ray_lib.cluster_resources(), collectors)
    return RayCollector(
        makers,
        policy,
        **kwargs,
        num_collectors=collectors,
        sync=True,
        ray_init_config=init,
        remote_configs={"num_cpus": 1, "memory": RAY_ACTOR_MEMORY},
        collector_kwargs=local,
        update_after_each_batch=True,
    )


# what each collector actor asks of the Ray cluster besides one CPU
RAY_ACTOR_MEMORY = 2 * 1024**3


def ray_init_config(ray: str, collectors: int) -> dict:
    """``ray.init``'s arguments for ``--ray``: a cluster's address ("auto" finds the
    running one), or "local": a new instance of this process's own with a CPU per
    collector, even where a cluster runs beside it (``address=None`` would join that
    cluster, which refuses ``num_cpus``)."""
    common = {"ignore_reinit_error": True, "log_to_driver": False}
    if ray == "local":
        return {"address": "local", "num_cpus": collectors, **common}
    return {"address": ray, **common}


def check_ray_fits(resources: dict, collectors: int) -> None:
    """Refuse collectors the cluster cannot place (each actor takes one CPU and
    :data:`RAY_ACTOR_MEMORY`): Ray would wait for them forever, with no message."""
    cpus, memory = resources.get("CPU", 0), resources.get("memory", 0)
    if cpus < collectors:
        raise ValueError(
            f"the Ray cluster has {cpus:g} CPUs and each of the {collectors} collectors needs one: give "
            f"--collectors {int(cpus)} or fewer, or a larger cluster"
        )
    if memory < collectors * RAY_ACTOR_MEMORY:
        raise ValueError(
            f"the Ray cluster has {memory / 2**30:.1f} GiB for tasks and each of the {collectors} collectors "
            f"asks {RAY_ACTOR_MEMORY / 2**30:g} GiB: give fewer --collectors, or a larger cluster"
        )


def horizon_bytes(
    env_id: str,
    horizon: int,
    members: int,
    *,
    params: dict | None = None,
    grad_checkpoint: bool = False,
    kept: int = 0,
) -> int:
    """About the memory the graph of ``horizon`` differentiated actions of ``members``
    members keeps (float32), from one action of one member measured here: that
    action's graph per action and member, or with ``grad_checkpoint`` what each action
    saves plus one action's whole graph, recomputed in the backward pass, but for the
    first ``kept`` actions, whose graphs are kept whole."""

    def one_action(checkpoint: bool) -> int:
        env = beacon_torch.make(env_id, 1, differentiable=True, grad_checkpoint=checkpoint, params=params or {})
        env.reset()
        action = env.null_action()
        if action.is_floating_point():
            action.requires_grad_()
        with saved_storages() as saved:
            env.step_members(action)
        return max(sum(saved.values()), env.physics.member_floats() * env.dtype.itemsize)

    whole = one_action(False)
    if not grad_checkpoint:
        return horizon * members * whole
    kept = min(kept, horizon)
    return kept * members * whole + (horizon - kept) * members * one_action(True) + members * whole
