"""The envs inside TorchRL's machinery: transforms, collectors, a policy module."""

import torch
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs import ObservationNorm, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import MLP, QValueActor

import beacon_torch


def test_transformed_env_with_observation_norm_and_step_counter():
    env = TransformedEnv(
        beacon_torch.make("vortex-v0", 4), ObservationNorm(in_keys=["observation"], standard_normal=True)
    )
    env.append_transform(StepCounter())
    env.transform[0].init_stats(num_iter=50, reduce_dim=(0, 1), cat_dim=1)
    check_env_specs(env)
    r = env.rollout(20)
    assert r["next", "step_count"][:, -1].flatten().tolist() == [20] * 4
    assert torch.isfinite(r["next", "observation"]).all()


def test_collector_over_the_batched_env():
    env = beacon_torch.make("vortex-v0", 8, seed=0)
    collector = Collector(env, policy=None, frames_per_batch=160, total_frames=480)
    sizes = [batch.numel() for batch in collector]
    collector.shutdown()
    assert sizes == [160, 160, 160]


def test_q_value_actor_on_the_discrete_env():
    env = beacon_torch.make("lorenz-v0", 4)
    net = MLP(in_features=6, out_features=3, num_cells=[16])
    actor = QValueActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["action_value"]), spec=env.action_spec_unbatched
    )
    r = env.rollout(10, policy=actor)
    assert r["action"].shape == (4, 10) and r["action"].dtype == torch.int64
