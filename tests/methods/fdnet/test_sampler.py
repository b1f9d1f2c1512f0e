import pytest
import torch

from fdnet.errors import ConfigError
from fdnet.methods.fdnet.sampler import DomainBalancedSampler


def test_batches_are_balanced_and_distinct_per_domain():
    s = DomainBalancedSampler([10, 5, 7], 4, generator=torch.Generator().manual_seed(1))
    batch = s.sample()
    assert batch.shape == (3, 4)
    for row, size in zip(batch, [10, 5, 7]):
        assert len(set(row.tolist())) == 4 and int(row.max()) < size
    assert s.domain_labels().tolist() == [0] * 4 + [1] * 4 + [2] * 4


def test_same_seed_same_batches():
    a = DomainBalancedSampler([20, 20], 3, generator=torch.Generator().manual_seed(3))
    b = DomainBalancedSampler([20, 20], 3, generator=torch.Generator().manual_seed(3))
    assert all(torch.equal(a.sample(), b.sample()) for _ in range(5))


def test_errors_name_the_problem():
    with pytest.raises(ConfigError, match="at least two conditions"):
        DomainBalancedSampler([10], 2, names=["summer"])
    with pytest.raises(ConfigError, match="'winter' has 3 training images"):
        DomainBalancedSampler([10, 3], 4, names=["summer", "winter"])
