"""rcotorch.engine.memo: a derived value is made again exactly when one of its tensors changed."""

import torch

from rcotorch.engine import memo


class Owner:
    pass


def test_derived_follows_replacement_and_in_place_changes():
    o, calls = Owner(), []
    t = torch.ones(3)

    def make():
        calls.append(1)
        return float(t.sum())

    assert memo.derived(o, "s", (t, "tag"), make) == 3.0
    assert memo.derived(o, "s", (t, "tag"), make) == 3.0 and len(calls) == 1
    t.mul_(2)                                                    # in place: its version moves
    assert memo.derived(o, "s", (t, "tag"), make) == 6.0 and len(calls) == 2
    assert memo.derived(o, "s", (t, "other"), make) == 6.0 and len(calls) == 3     # another plain value
    t = torch.ones(3)                                            # replaced (same values)
    assert memo.derived(o, "s", (t, "other"), make) == 3.0 and len(calls) == 4
    memo.remember(o, "s", (t, "other"), 42.0)
    assert memo.derived(o, "s", (t, "other"), make) == 42.0 and len(calls) == 4
    memo.forget(o)
    assert memo.derived(o, "s", (t, "other"), make) == 3.0 and len(calls) == 5
