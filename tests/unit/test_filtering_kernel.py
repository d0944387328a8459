"""The compiled index step (services/filtering/kernel.py) against the numpy form it replaces.

Same maths, another order of operations: equal to rounding (relative 1e-10), on many
segments with two posterior groups, a nonzero b, a correlated R and uneven weights; and
one segment's numbers do not depend on the rows stepped with it, on all cores or alone on
the calling thread (bit for bit).
"""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from test_filter_core import random_params

from services.filtering import fold as fold_module
from services.filtering.banks import CUSUM_THRESHOLD, Banks, RowParams, Scratch
from services.filtering.degradation import DegradationParams
from services.filtering.events import INDEX, RESTART, TAMPING, Event
from services.filtering.fold import fold_many, fold_many_counted
from services.filtering.kalman import ObservationModel
from services.filtering.kernel import PARALLEL_ROWS
from services.filtering.models import Models
from services.filtering.state import Filtered, pack_state, state_layout, unpack_state

FIELDS = ("mu", "sigma", "z_plus", "sigma_z_plus")

NS, SEGMENTS = 20, PARALLEL_ROWS + 4  # a batch this size runs on every core


def banks_and_inputs(seed: int):
    rng = np.random.default_rng(seed)
    starts = []
    for _ in range(SEGMENTS):
        z = rng.normal(1.0, 0.2, (NS, 2))
        A = rng.normal(0, 0.05, (NS, 2, 2))
        P = A @ np.swapaxes(A, -1, -2) + 1e-4 * np.eye(2)
        starts.append(Filtered(z, P, 1e9, 1e9, 0, None, rng.normal(0, 2.0, NS)))
    groups = [random_params(rng, (), NS, 2) for _ in range(2)]
    params = RowParams([groups[k % 2] for k in range(SEGMENTS)])
    obs = ObservationModel(
        np.array([[0.9, 0.1], [0.05, 1.1]]),
        np.array([0.1, -0.05]),
        np.array([[0.02, 0.005], [0.005, 0.03]]),
    )
    rows = np.arange(SEGMENTS)[::-1].copy()
    t_s = 1e9 + rng.uniform(0.5, 30.0, SEGMENTS) * 86_400.0
    y = rng.normal(1.0, 0.3, (SEGMENTS, 2))
    last = rng.uniform(size=SEGMENTS) < 0.7
    return starts, params, obs, rows, t_s, y, last


def test_the_compiled_step_is_the_numpy_step_to_rounding():
    starts, params, obs, rows, t_s, y, last = banks_and_inputs(1)
    compiled, numpy_form = Banks(starts, NS, 2), Banks(starts, NS, 2)
    compiled.index_compiled(rows, t_s, y, params, obs, last)
    numpy_form.index_numpy(rows, t_s, y, params, obs, last)
    for name in ("z", "P", "log_w", "t_s", "nis", "cusum", "cusum_t0", "cusum_t1"):
        a, b = getattr(compiled, name), getattr(numpy_form, name)
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12, err_msg=name)
    assert np.isnan(compiled.nis[rows[~last]]).all()  # only the last update's NIS is written
    assert (compiled.n_updates == numpy_form.n_updates).all()
    assert np.array_equal(compiled.P[..., 0, 1], compiled.P[..., 1, 0])
    assert not np.allclose(compiled.z, Banks(starts, NS, 2).z)  # it did step


def test_a_segment_gets_the_same_bits_alone_or_in_a_batch():
    starts, params, obs, rows, t_s, y, last = banks_and_inputs(2)
    together = Banks(starts, NS, 2)
    together.index_compiled(rows, t_s, y, params, obs, last)
    for r in range(0, SEGMENTS, 7):
        alone = Banks(starts, NS, 2)
        one = rows[r : r + 1]
        alone.index_compiled(one, t_s[r : r + 1], y[r : r + 1], params, obs, last[r : r + 1])
        row = rows[r]
        for name in ("z", "P", "log_w", "nis", "cusum"):
            assert np.array_equal(
                getattr(alone, name)[row], getattr(together, name)[row], equal_nan=True
            ), name


def _index_log(t_s: float, y) -> list[Event]:
    return [Event(INDEX, t_s, ("index", "T1", "u1", t_s), np.asarray(y, dtype=float), None)]


def test_a_folded_state_is_one_buffer_that_packs_to_the_same_bytes():
    starts, params, obs, rows, t_s, y, _last = banks_and_inputs(3)
    ps = [DegradationParams(*(getattr(params.stack, f)[k % 2] for f in FIELDS)) for k in range(4)]
    logs = [_index_log(t_s[k], y[k]) for k in range(4)]
    folded = fold_many(starts[:4], logs, ps, obs)
    for before, state in zip(starts[:4], folded, strict=True):
        assert before.flat is None and state.flat is not None
        width = state_layout(NS, 2)[2]
        assert state.flat.shape == (width,)
        for name in ("z", "P", "log_w"):
            assert np.shares_memory(getattr(state, name), state.flat), name
        assert np.array_equal(state.buffer(), replace(state, flat=None).buffer())
        again = unpack_state(pack_state(state))
        assert pack_state(again) == pack_state(state)
        assert pack_state(replace(state, flat=None)) == pack_state(state)
        assert np.shares_memory(again.z, again.flat) and np.array_equal(again.P, state.P)


def test_a_fold_in_a_scratch_copies_its_states_out():
    starts, params, obs, rows, t_s, y, _last = banks_and_inputs(4)
    ps = [DegradationParams(*(getattr(params.stack, f)[k % 2] for f in FIELDS)) for k in range(8)]
    logs = [_index_log(t_s[k], y[k]) for k in range(8)]
    scratch = Scratch()
    first = fold_many(starts[:8], logs, ps, obs, scratch)
    kept = [pack_state(state) for state in first]
    # a second fold in the same scratch (other rows, other data) leaves the first's alone
    later = [_index_log(t_s[k] + 86_400.0, y[k] + 0.5) for k in range(8)]
    second = fold_many(first, later, ps, obs, scratch)
    assert [pack_state(state) for state in first] == kept
    without = fold_many(starts[:8], logs, ps, obs)  # views of its own stacked arrays
    assert [pack_state(state) for state in without] == kept
    assert not any(np.shares_memory(a.flat, b.flat) for a in first for b in second)


def _mixed_logs(rng: np.random.Generator, segments: int) -> list[list[Event]]:
    """Logs of every shape a fold meets: an index before any start, TRC restarts, tampings,
    indices of two units, runs of low readings (the CUSUM climbs), equal times."""
    logs = []
    for s in range(segments):
        log, t = [], 1e9 + s
        if s % 5 == 0:
            log.append(Event(INDEX, t, ("index",), np.array([1.0, 0.8]), SimpleNamespace(
                train="T1", unit="u1")))  # fmt: skip
        for _ in range(rng.integers(1, 4)):
            t += 86_400.0
            if rng.uniform() < 0.6 or not log:
                log.append(Event(RESTART, t, ("trc",), rng.normal([1.2, 0.9], 0.1), None))
            else:
                log.append(Event(TAMPING, t, ("maintenance",), None, None))
            low = rng.uniform() < 0.3
            for _ in range(rng.integers(0, 30)):
                t += float(rng.choice([0.0, 86_400.0 * rng.uniform(0.5, 9.0)]))
                y = rng.normal([0.2, 0.1] if low else [1.2, 0.9], 0.1)
                unit = SimpleNamespace(train="T1", unit=str(rng.choice(["u1", "u2"])))
                log.append(Event(INDEX, t, ("index",), y, unit))
        logs.append(log)
    return logs


@pytest.mark.parametrize("halt", [None, CUSUM_THRESHOLD])
def test_the_fold_as_runs_is_the_fold_by_steps_bit_for_bit(monkeypatch, halt):
    starts, params, obs, *_ = banks_and_inputs(5)
    other = ObservationModel(obs.H * 1.1, obs.b + 0.02, obs.R * 0.9)
    models = Models(observation=obs, unit_observations={("T1", "u2"): other})
    logs = _mixed_logs(np.random.default_rng(6), 80)
    ps = [DegradationParams(*(getattr(params.stack, f)[k % 2] for f in FIELDS)) for k in range(80)]
    firsts = [None if k % 3 else starts[k] for k in range(80)]  # some started, some not
    runs = fold_many_counted(firsts, logs, ps, models, halt)
    monkeypatch.setattr(fold_module, "_fold_runs", fold_module._fold_steps)
    steps = fold_many_counted(firsts, logs, ps, models, halt)
    assert runs[1] == steps[1]  # events folded per segment (fewer where halted)
    if halt is not None:
        assert any(count < len(log) for count, log in zip(runs[1], logs, strict=True))
    for a, b in zip(runs[0], steps[0], strict=True):
        assert (a is None) == (b is None)
        if a is not None:
            assert pack_state(a) == pack_state(b)
