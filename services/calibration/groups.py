r"""Posterior groups: which groups exist, what each pools, when one is rebuilt, and the
bound on a pooled group moved by one segment. Pure.

Degradation posteriors
    Per segment, the TRC history (``z`` at record times) and the tampings (known time, or the
    middle of the interval: the paper's mid-interval rule) give increments that do not span a
    tamping and post-tamping levels (:func:`history_to_increments`). Groups:

    * ``seg.{line}.{segment}`` when the segment alone has ``>= segment_min_increments``;
    * ``line.{line}`` pooling the increments of the line's segments;
    * ``net`` pooling every segment.

    Post-tamping levels come from the group itself when it has ``>= min_levels``, else from
    its line, else from the network; when even the network has fewer, ``(z+, Σz+)`` are drawn
    from the level prior alone (``n_levels = 0``) so that drift and diffusion are published
    before any tamping has been recorded. ``samples`` draws of :func:`sample_degradation_posterior`
    use a generator seeded from ``(seed, group, version)``: re-running gives identical samples.
    A group is rebuilt when a fingerprint of its inputs (increments, levels, and the settings
    that shape the draws) changed; when the core raises :class:`CalibrationError` (too little
    data) the old posterior stays and the refusal is counted.

Records of some indicators only
    A group whose segments have records of some indicators only (a level-only TRC car) is
    drawn from :func:`partial_drift_posterior`: the indicator ``j`` that the most of those
    records measured gets every one of its increments, the others their increments between
    complete records (exact; see :class:`PartialDriftPosterior`). The records that did not
    measure ``j`` (alignment-only records in a group whose partial records are mostly
    level-only) are left out of the group's drift and diffusion: with both kinds the
    posterior has no closed form, and they are counted in ``left_out``. Post-tamping levels
    come from complete records only (``z+`` is a joint level). ``n_increments`` of such a
    posterior counts the increments of ``j``.

"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from schemas import INDICATORS, DegradationPosterior, NDArray
from schemas.keys import SegmentId
from services.calibration.config import CalibratorConfig
from services.calibration.moves import Move, largest_move
from services.calibration.posterior import (
    SegmentIncrements,
    group_rng,
    partial_drift_posterior,
    sample_post_tamping,
    sample_prior,
)
from services.calibration.state import ModelEntry
from services.drift_diffusion import CalibrationError, NIWPrior, posterior_drift_diffusion

_N = len(INDICATORS)


@dataclass(frozen=True)
class GroupInput:
    """What one group's posterior is built from."""

    dz: np.ndarray
    dt: np.ndarray
    level: np.ndarray
    age: np.ndarray
    level_source: str  # the group whose levels are used, or "prior"
    t_newest: float  # epoch s of the newest TRC record used of the group's segments
    members: tuple[SegmentId, ...] = ()  # segments whose increments are pooled
    # records of some indicators only: the indicator j all of whose increments are used and
    # those increments (dz_j, dt_j), None when every record is complete
    chain: tuple[int, np.ndarray, np.ndarray] | None = None
    left_out: int = 0  # records of some indicators only that did not measure j


def _chain(incs: list[SegmentIncrements]) -> tuple[tuple[int, np.ndarray, np.ndarray] | None, int]:
    """The indicator whose increments a pool of segments uses from its partial records, with
    them, and the number of partial records left out; (None, 0) when every record is
    complete."""
    partial = [i for i in incs if i.chains]
    if not partial:
        return None, 0
    j = int(np.argmax(np.sum([i.partial_with for i in partial], axis=0)))
    dz = np.concatenate([i.chains[j][0] if i.chains else i.dz[:, j] for i in incs])
    dt = np.concatenate([i.chains[j][1] if i.chains else i.dt for i in incs])
    return (j, dz, dt), sum(i.partial_without[j] for i in partial)


def group_inputs(
    increments: Mapping[SegmentId, SegmentIncrements],
    newest_used: Mapping[SegmentId, float],
    cfg: CalibratorConfig,
) -> dict[str, GroupInput]:
    """Inputs of every group that exists now (deterministic order of pooling)."""
    segs = sorted(increments)
    newest = newest_used

    def pool(members: list[SegmentId]):
        incs = [increments[s] for s in members]
        return (
            np.concatenate([i.dz for i in incs]).reshape(-1, _N),
            np.concatenate([i.dt for i in incs]),
            np.concatenate([i.level for i in incs]).reshape(-1, _N),
            np.concatenate([i.age for i in incs]),
            max(newest[s] for s in members),
            tuple(members),
            *_chain(incs),
        )

    net = pool(segs)
    lines: dict[str, list[SegmentId]] = {}
    for s in segs:
        lines.setdefault(s[0], []).append(s)
    line_pool = {line: pool(members) for line, members in lines.items()}

    def make(own, sources: list[tuple[str, tuple]]) -> GroupInput:
        dz, dt, _, _, t_newest, members, chain, left_out = own
        for source, (_, _, level, age, *_) in sources:
            if len(level) >= cfg.min_levels:
                return GroupInput(dz, dt, level, age, source, t_newest, members, chain, left_out)
        return GroupInput(
            dz, dt, net[2][:0], net[3][:0], "prior", t_newest, members, chain, left_out
        )

    out: dict[str, GroupInput] = {"net": make(net, [("net", net)])}
    for line, lp in line_pool.items():
        out[f"line.{line}"] = make(lp, [(f"line.{line}", lp), ("net", net)])
    for s in segs:
        inc = increments[s]
        if max([len(inc.dt)] + [len(dt) for _, dt in inc.chains]) >= cfg.segment_min_increments:
            own = pool([s])
            group = f"seg.{s[0]}.{s[1]}"
            out[group] = make(own, [(group, own), (f"line.{s[0]}", line_pool[s[0]]), ("net", net)])
    return out


def fingerprint(group: str, g: GroupInput, cfg: CalibratorConfig) -> str:
    """What a group's posterior is drawn from: its inputs and the settings that shape the draws."""
    h = hashlib.sha256()
    settings = (
        group,
        g.level_source,
        cfg.samples,
        cfg.seed,
        cfg.min_increments,
        cfg.min_levels,
    )
    h.update(repr(settings).encode())
    for prior in (cfg.drift_prior, cfg.level_prior):
        if prior is not None:
            h.update(
                repr((prior.m0.tolist(), prior.lambda0, prior.Psi0.tolist(), prior.nu0)).encode()
            )
    arrays = [g.dz, g.dt, g.level, g.age]
    if g.chain is not None:
        h.update(repr(("chain", g.chain[0])).encode())
        arrays += [g.chain[1], g.chain[2]]
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
        h.update(repr(a.shape).encode())
    return h.hexdigest()


def one_segment_move(
    g: GroupInput,
    post: DegradationPosterior,
    in_force: ModelEntry,
    increments: Mapping[SegmentId, SegmentIncrements],
    cfg: CalibratorConfig,
) -> tuple[str, SegmentId] | None:
    r"""The move bound: why the pooled posterior ``post`` moved too far on the strength of
    one segment and that segment, or None.

    The move is :math:`\max |\bar\theta_{new} - \bar\theta_{old}| / sd(\theta_{old})`
    over the elements of ``mu`` and ``Sigma``, in the posterior sd of the version in force
    (from its draws). Beyond ``max_move_sd`` the conjugate posterior means are computed
    again without each member segment in turn; when leaving out one segment brings the
    move back within the bound (or the group has one segment only and a prior in force),
    that segment alone moved it: the candidate is held (not published) and the segment's
    newest record reported (by the caller). Segment groups, and a pooled group of one segment whose
    version in force came from data, are not judged (their data are one segment's own).
    """
    if post.group.startswith("seg."):
        return None
    old: DegradationPosterior = in_force.message  # type: ignore[assignment]
    o_mu, o_sigma = old.mu.array(), old.sigma.array()
    ref = (o_mu.mean(axis=0), o_mu.std(axis=0), o_sigma.mean(axis=0), o_sigma.std(axis=0))

    def move(mu, sigma) -> Move:
        return largest_move([("mu", mu, ref[0], ref[1]), ("sigma", sigma, ref[2], ref[3])])

    bound = cfg.max_move_sd
    moved = move(post.mu.array().mean(axis=0), post.sigma.array().mean(axis=0))
    if moved[0] <= bound:
        return None
    members = [s for s in g.members if len(increments[s].dt)]
    if not members:
        return None  # no complete increments: nothing to leave out in turn
    if len(members) == 1 and old.n_increments > 0:
        return None  # a one-segment group from data: it moves with its segment
    culprit: SegmentId | None = members[0] if len(members) == 1 else None
    if culprit is None:
        best = (math.inf, members[0])
        for s in members:
            rest = [increments[m] for m in members if m != s]
            try:
                p = posterior_drift_diffusion(
                    np.concatenate([i.dz for i in rest]).reshape(-1, _N),
                    np.concatenate([i.dt for i in rest]),
                    cfg.drift_prior,
                    min_increments=1,
                )
            except CalibrationError:
                continue
            without = move(p.m, p.mean_sigma())[0]
            best = min(best, (without, s))
        if best[0] <= bound:
            culprit = best[1]
    if culprit is None:
        return None  # several segments agree: a real change
    why = (
        f"posterior {post.group} not published: moved {moved[1]} of version "
        f"{old.version} in force (more than {bound:g}) on the strength of segment "
        f"{culprit[0]}/{culprit[1]} alone"
    )
    return why, culprit


def build_posterior(
    group: str, g: GroupInput, version: int, cfg: CalibratorConfig
) -> DegradationPosterior:
    """Version ``version`` of ``group``'s posterior from its inputs; raises CalibrationError."""
    rng = group_rng(cfg.seed, group, version)
    min_inc = cfg.segment_min_increments if group.startswith("seg.") else cfg.min_increments
    if g.chain is None:
        post = posterior_drift_diffusion(g.dz, g.dt, cfg.drift_prior, min_increments=min_inc)
    else:
        j, dz_j, dt_j = g.chain
        post = partial_drift_posterior(
            g.dz, g.dt, j, dz_j, dt_j, cfg.drift_prior, min_increments=min_inc
        )
    mu, sigma = post.sample(cfg.samples, rng)
    if g.level_source != "prior":
        z_plus, sigma_z_plus = sample_post_tamping(
            g.level, g.age, mu, rng, cfg.level_prior, min_levels=cfg.min_levels
        )
    else:
        level_prior = cfg.level_prior or NIWPrior.default_level(_N)
        z_plus, sigma_z_plus = sample_prior(level_prior, cfg.samples, rng)
    return DegradationPosterior(
        group=group,
        version=version,
        t=g.t_newest,
        indicators=list(INDICATORS),
        mu=NDArray.of(mu),
        sigma=NDArray.of(sigma),
        z_plus=NDArray.of(z_plus),
        sigma_z_plus=NDArray.of(sigma_z_plus),
        n_increments=post.n_obs,
        n_levels=len(g.age),
    )
