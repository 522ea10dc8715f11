"""ParamGroup's learning-rate schedule, as a pure function of the step."""

import pytest

from rainyscape.components import ParamGroup


def group(**kw):
    return ParamGroup("g", [], lr=0.1, **kw)


def test_constant_rate_without_decay_or_anneal():
    assert group().lr_at(0, 100) == group().lr_at(99, 100) == 0.1


def test_decay_spans_the_run_or_its_own_steps():
    assert group(lr_decay=0.5).lr_at(100, 100) == pytest.approx(0.05)
    assert group(lr_decay=0.5, lr_decay_steps=50).lr_at(100, 100) == pytest.approx(0.025)


def test_anneal_leaves_the_run_alone_until_its_start_then_reaches_its_factor():
    g = group(lr_decay=0.5, anneal_at=0.9, anneal_to=0.1)
    plain = group(lr_decay=0.5)
    for step in (0, 50, 90):
        assert g.lr_at(step, 100) == pytest.approx(plain.lr_at(step, 100))
    assert g.lr_at(95, 100) == pytest.approx(plain.lr_at(95, 100) * 0.1 ** 0.5)
    assert g.lr_at(100, 100) == pytest.approx(plain.lr_at(100, 100) * 0.1)
    rates = [g.lr_at(s, 100) for s in range(90, 101)]
    assert all(a > b for a, b in zip(rates, rates[1:]))
