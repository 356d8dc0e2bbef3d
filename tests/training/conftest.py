import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.data import TRAJ_KEY
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble


def linear_episodes(
    episodes: int,
    steps: int,
    seed: int = 0,
    sigma: float = 0.05,
    gain: float = 0.5,
    first: int = 0,
    drift: float = 0.0,
) -> TensorDict:
    """Flat episodes of s' = A s + B a + sigma * eps (3-D state, 1-D action; ``gain``: how
    hard the action pushes the third dimension; ``drift``: a constant push on it every step, a
    slope), ids from ``first`` on."""
    g = torch.Generator().manual_seed(seed)
    a_mat = torch.tensor([[0.9, 0.1, 0.0], [0.0, 0.9, 0.1], [0.0, 0.0, 0.8]])
    b_mat = torch.tensor([[0.0], [0.0], [gain]])
    s = torch.randn(episodes, 3, generator=g)
    obs, act, nxt = [], [], []
    for _ in range(steps):
        a = torch.rand(episodes, 1, generator=g) * 2 - 1
        s_next = s @ a_mat.T + a @ b_mat.T + sigma * torch.randn(episodes, 3, generator=g)
        s_next[:, 2] += drift
        obs.append(s), act.append(a), nxt.append(s_next)
        s = s_next
    data = TensorDict(
        {
            "observation": torch.stack(obs, 1),
            "action": torch.stack(act, 1),
            ("next", "observation"): torch.stack(nxt, 1),
            TRAJ_KEY: (torch.arange(episodes) + first)[:, None].expand(episodes, steps),
        },
        batch_size=[episodes, steps],
    )
    data["next", "done"] = torch.zeros(episodes, steps, 1, dtype=torch.bool)
    data["next", "done"][:, -1] = True
    return data.reshape(-1)


@pytest.fixture(scope="session")
def linear_data():
    train = linear_episodes(12, 40, seed=0)
    val = linear_episodes(4, 40, seed=1)
    val[TRAJ_KEY] += 100
    return train, val


@pytest.fixture
def small_ensemble():
    """Factory of small ensembles for the 3-D linear system."""

    def make(members: int = 3, seed: int = 0) -> RCVAEEnsemble:
        torch.manual_seed(seed)
        config = RCVAEConfig(3, 1, hidden_dim=16, latent_dim=2, mlp_dim=16)
        return RCVAEEnsemble(config, members)

    return make
