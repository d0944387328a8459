"""A segment's filter state (:class:`Filtered`): its ``Ns`` samples' ``z``, ``P`` and log
weights in one float64 buffer (:func:`state_layout`), its scalars, and its stored bytes
(:func:`pack_state`)."""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np


def state_layout(ns: int, n: int) -> tuple[int, int, int]:
    """Where a segment's ``z`` (Ns, n), ``P`` (Ns, n, n) and ``log_w`` (Ns) lie in its one
    float64 buffer (:attr:`Filtered.flat`, a row of :attr:`Banks.F`, the arrays of a
    stored checkpoint): ``(start of P, start of log_w, width)``, each array row-major."""
    return ns * n, ns * n + ns * n * n, ns * (n + n * n + 1)


def state_views(flat: np.ndarray, ns: int, n: int):
    """``(z, P, log_w)`` as views of ``flat`` ((W,) one segment, or (S, W) stacked rows)."""
    at_p, at_w, width = state_layout(ns, n)
    if flat.shape[-1] != width:
        raise ValueError(f"state buffer of width {flat.shape[-1]}, not {width} (Ns={ns}, n={n})")
    lead = flat.shape[:-1]
    z = np.reshape(flat[..., :at_p], (*lead, ns, n), copy=False)
    P = np.reshape(flat[..., at_p:at_w], (*lead, ns, n, n), copy=False)
    return z, P, flat[..., at_w:]


@dataclass(frozen=True)
class Filtered:
    """The filter bank of one segment after the last event of its log.

    ``flat``, when set, is the one buffer whose views ``z``, ``P`` and ``log_w`` are
    (:func:`state_layout`): a fold then copies each state in and out as one array rather
    than three."""

    z: np.ndarray  # (Ns, n)
    P: np.ndarray  # (Ns, n, n)
    t_s: float  # epoch s of the last applied event
    last_trc_t: float | None
    n_updates: int
    nis: float | None
    log_w: np.ndarray  # (Ns,) log-likelihood of the on-board data since the TRC restart
    cusum: float = 0.0  # one-sided CUSUM of the indices reading lower than predicted
    cusum_t0: float = float("nan")  # the last index (or start) at which the CUSUM was 0
    cusum_t1: float = float("nan")  # the first index after it (NaN while the CUSUM is 0)
    # bit i set: indicator i was not measured by the last TRC record (0: all were, or none yet)
    trc_absent: int = 0
    flat: np.ndarray | None = field(default=None, repr=False, compare=False)

    def buffer(self) -> np.ndarray:
        """``z``, ``P`` and ``log_w`` in one (W,) float64 array (``flat`` or a new one)."""
        if self.flat is not None:
            return self.flat
        return np.concatenate([self.z.ravel(), self.P.ravel(), self.log_w.ravel()])

    @staticmethod
    def of_buffer(flat: np.ndarray, ns: int, n: int, *scalars: Any) -> Filtered:
        """A state on ``flat`` (W,) contiguous (:func:`state_layout`); ``scalars``: ``t_s``
        to ``trc_absent`` in field order. Made without the frozen dataclass's ``__init__``
        and its eleven guarded assignments (a fold makes one per segment); the same
        object."""
        at_p, at_w, width = state_layout(ns, n)
        if flat.shape != (width,):
            raise ValueError(f"state buffer of shape {flat.shape}, not ({width},) (Ns={ns})")
        return Filtered._on_buffer(flat, ns, n, at_p, at_w, *scalars)

    @staticmethod
    def _on_buffer(flat, ns, n, at_p, at_w, t_s, last_trc_t, n_updates, nis, cusum, cusum_t0,
                   cusum_t1, trc_absent=0) -> Filtered:  # fmt: skip
        """:meth:`of_buffer` with ``flat``'s shape known and its layout given."""
        new = object.__new__(Filtered)
        new.__dict__.update(
            z=flat[:at_p].reshape(ns, n),  # views: flat is one contiguous row
            P=flat[at_p:at_w].reshape(ns, n, n),
            t_s=t_s,
            last_trc_t=last_trc_t,
            n_updates=n_updates,
            nis=nis,
            log_w=flat[at_w:],
            cusum=cusum,
            cusum_t0=cusum_t0,
            cusum_t1=cusum_t1,
            trc_absent=trc_absent,
            flat=flat,
        )
        return new


def stack_rows(arrays: Sequence[np.ndarray], out: np.ndarray | None = None) -> np.ndarray:
    """``np.stack(arrays)`` of equal-shaped arrays, as one concatenation (``np.stack``
    expands each array in Python first, slow on many small states), into ``out`` if given
    (its first ``len(arrays)`` rows)."""
    shape = arrays[0].shape
    if not all(a.shape == shape for a in arrays):
        raise ValueError(f"cannot stack arrays of shapes {sorted({a.shape for a in arrays})}")
    if out is None:
        return np.concatenate(arrays).reshape(len(arrays), *shape)
    rows = out[: len(arrays)]
    np.concatenate(arrays, out=rows.reshape(-1))
    return rows


# ns, n; t_s, last_trc_t, nis, cusum; n_updates; cusum_t0, cusum_t1, trc_absent
_STATE_HEAD = struct.Struct("<2I 4d q 3d")


def pack_state(state: Filtered) -> bytes:
    """A Filtered state as bytes: header, then z, P, log_w as exact little-endian float64
    (None of ``last_trc_t``/``nis`` as NaN, as the batched bank holds them)."""
    ns, n = state.z.shape
    head = _STATE_HEAD.pack(
        ns,
        n,
        state.t_s,
        math.nan if state.last_trc_t is None else state.last_trc_t,
        math.nan if state.nis is None else state.nis,
        state.cusum,
        state.n_updates,
        state.cusum_t0,
        state.cusum_t1,
        float(state.trc_absent),
    )
    return head + np.ascontiguousarray(state.buffer(), dtype="<f8").tobytes()


def unpack_state(blob: bytes) -> Filtered:
    """:func:`pack_state` back; ValueError if the bytes are not one."""
    try:
        ns, n, t_s, trc, nis, cusum, n_updates, t0, t1, absent = _STATE_HEAD.unpack_from(blob)
    except struct.error as exc:
        raise ValueError(f"state: {exc}") from None
    sizes = (ns * n, ns * n * n, ns)
    if len(blob) != _STATE_HEAD.size + 8 * sum(sizes) or ns < 1 or n < 1:
        raise ValueError(f"state: {len(blob)} bytes for Ns={ns}, n={n}")
    flat = np.frombuffer(blob, dtype="<f8", offset=_STATE_HEAD.size).astype(np.float64)
    trc_t = None if math.isnan(trc) else trc
    nis_or_none = None if math.isnan(nis) else nis
    scalars = (t_s, trc_t, int(n_updates), nis_or_none, cusum, t0, t1, int(absent))
    return Filtered.of_buffer(flat, ns, n, *scalars)
