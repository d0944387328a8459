"""The measurement-frequency study of the paper's section 4.2 (Table 2, Fig. 7), on the core.

Procedure per scenario (fast, typical, slow) and path p = 1..P:

0. Draw a segment from the scenario's population: true drift and diffusion, and a TRC
   history of ``history.increments`` increments every 8-11 weeks; its conjugate NIW
   posterior gives the Ns parameter samples the filter bank runs on (Eq. 13).
1. From the TRC record at t = 0, draw the true weekly path z_1..z_K from the Wiener model
   with the true parameters (Eq. 1-2).
2. Draw on-board indices y_k = H z_k + b + e_k, e_k ~ N(0, R) (Eq. 3-4).
3. For every on-board interval (1, 2, 4, 8 weeks, none), run the filter bank (all paths ×
   all samples at once): predict every week, update in the weeks the interval hits (Eq. 7-12).
4. Summarise the mixture every week: W_k = |P_k|^(1/n) of the total covariance (Eq. 14) and
   the 95 % marginal credible-interval width in log space per indicator at the report weeks.

The same paths and indices are used for every interval, so differences between intervals
are the effect of the interval, not of sampling noise. The paths contain no tamping: the
study starts at a TRC record and looks one year ahead.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.defaults import default_file
from services.drift_diffusion import posterior_drift_diffusion
from services.filtering.degradation import DegradationParams, transition_unchecked
from services.filtering.kalman import update_unchecked
from services.filtering.mixture import summarize
from services.runtime.config import read_json5

INDICATOR_NAMES = ("Top", "Align")
DEFAULT_CONFIG = default_file("study.json5")
WEEK_DAYS = 7.0


@dataclass(frozen=True)
class Scenario:
    """A population of segments: nominal drift, diffusion and level at the TRC record."""

    name: str
    mu: np.ndarray  # (n,) per day
    sigma: np.ndarray  # (n, n) per day
    z0: np.ndarray  # (n,) ln mm
    mu_spread: float  # sd of ln(true mu / mu)
    sigma_spread: float  # sd of ln(true sigma scale)


@dataclass(frozen=True)
class StudyConfig:
    paths: int
    weeks: int
    intervals_weeks: tuple[int, ...]  # 0 = no on-board data
    report_weeks: tuple[int, ...]
    posterior_samples: int
    seed: int
    history_increments: int
    history_interval_days: tuple[float, float]
    H: np.ndarray
    b: np.ndarray
    R: np.ndarray
    scenarios: tuple[Scenario, ...]


def load_study_config(path: str | Path = DEFAULT_CONFIG, **overrides) -> StudyConfig:
    """Read a study config (JSON5); keyword overrides replace top-level entries."""
    given = {key: value for key, value in overrides.items() if value is not None}
    raw = {**read_json5(path), **given}
    scenarios = []
    for name, s in raw["scenarios"].items():
        sd = np.asarray(s["sigma_sd"], float)
        corr = np.array([[1.0, s["corr"]], [s["corr"], 1.0]])
        scenarios.append(
            Scenario(
                name=name,
                mu=np.asarray(s["mu"], float),
                sigma=corr * np.outer(sd, sd),
                z0=np.log(np.asarray(s["z0_mm"], float)),
                mu_spread=float(s["mu_spread"]),
                sigma_spread=float(s["sigma_spread"]),
            )
        )
    obs = raw["observation"]
    config = StudyConfig(
        paths=int(raw["paths"]),
        weeks=int(raw["weeks"]),
        intervals_weeks=tuple(int(i) for i in raw["intervals_weeks"]),
        report_weeks=tuple(int(w) for w in raw["report_weeks"]),
        posterior_samples=int(raw["posterior_samples"]),
        seed=int(raw["seed"]),
        history_increments=int(raw["history"]["increments"]),
        history_interval_days=tuple(float(d) for d in raw["history"]["interval_days"]),
        H=np.asarray(obs["H"], float),
        b=np.asarray(obs["b"], float),
        R=np.asarray(obs["R"], float),
        scenarios=tuple(scenarios),
    )
    if config.paths < 2 or config.weeks < 1 or config.posterior_samples < 1:
        raise ValueError("paths, weeks and posterior_samples must be positive (paths >= 2)")
    if any(i < 0 for i in config.intervals_weeks):
        raise ValueError(f"intervals_weeks: negative interval in {config.intervals_weeks}")
    if not all(1 <= w <= config.weeks for w in config.report_weeks):
        raise ValueError(f"report_weeks: {config.report_weeks} outside 1..{config.weeks}")
    return config


@dataclass(frozen=True)
class ScenarioResult:
    name: str
    width: np.ndarray  # (intervals, paths, weeks + 1): W_k, Eq. 14
    ci_width: np.ndarray  # (intervals, paths, report weeks, n): 95 % CI width in log space


@dataclass(frozen=True)
class StudyResult:
    config: StudyConfig
    scenarios: tuple[ScenarioResult, ...]


def draw_segments(scenario: Scenario, config: StudyConfig, rng: np.random.Generator):
    """True parameters of P segments and the Ns-sample posterior built from their TRC history.

    Returns ``(true_mu (P, n), true_sigma (P, n, n), params)`` with params of shape (P, Ns, ·).
    """
    n, paths, ns = scenario.mu.size, config.paths, config.posterior_samples
    true_mu = scenario.mu * np.exp(scenario.mu_spread * rng.standard_normal((paths, n)))
    scale = np.exp(scenario.sigma_spread * rng.standard_normal(paths))
    true_sigma = scale[:, None, None] * scenario.sigma
    chol = np.linalg.cholesky(true_sigma)
    lo, hi = config.history_interval_days
    dt = rng.uniform(lo, hi, (paths, config.history_increments))
    noise = np.einsum("pij,pkj->pki", chol, rng.standard_normal(dt.shape + (n,)))
    dz = true_mu[:, None, :] * dt[..., None] + np.sqrt(dt)[..., None] * noise
    mu = np.empty((paths, ns, n))
    sigma = np.empty((paths, ns, n, n))
    for p in range(paths):  # one small conjugate update per segment, not per sample
        mu[p], sigma[p] = posterior_drift_diffusion(dz[p], dt[p]).sample(ns, rng)
    # The study's paths contain no tamping, so the reset parameters never enter a prediction.
    z_plus = np.broadcast_to(scenario.z0, (paths, ns, n))
    sigma_z_plus = np.zeros((paths, ns, n, n))
    return true_mu, true_sigma, DegradationParams(mu, sigma, z_plus, sigma_z_plus)


def run_scenario(
    scenario: Scenario,
    config: StudyConfig,
    rng: np.random.Generator,
    on_interval_done: Callable[[], None] | None = None,
) -> ScenarioResult:
    """Steps 0-4 of the module docstring for one scenario."""
    n, paths, weeks, ns = scenario.mu.size, config.paths, config.weeks, config.posterior_samples
    true_mu, true_sigma, params = draw_segments(scenario, config, rng)
    chol = np.linalg.cholesky(true_sigma)
    steps = np.einsum("pij,pkj->pki", chol, rng.standard_normal((paths, weeks, n)))
    z_true = scenario.z0 + np.cumsum(
        true_mu[:, None, :] * WEEK_DAYS + np.sqrt(WEEK_DAYS) * steps, axis=1
    )
    noise = rng.multivariate_normal(np.zeros(len(config.b)), config.R, (paths, weeks))
    y = z_true @ config.H.T + config.b + noise  # (paths, weeks, m)

    report = {w: i for i, w in enumerate(config.report_weeks)}
    width = np.zeros((len(config.intervals_weeks), paths, weeks + 1))
    ci_width = np.zeros((len(config.intervals_weeks), paths, len(report), n))
    for i, interval in enumerate(config.intervals_weeks):
        z = np.broadcast_to(scenario.z0, (paths, ns, n)).copy()
        P = np.zeros((paths, ns, n, n))
        dt = np.full(paths, WEEK_DAYS)
        for week in range(1, weeks + 1):
            z, P = transition_unchecked(z, P, params, dt)
            if interval and week % interval == 0:
                z, P, _ = update_unchecked(z, P, y[:, week - 1], config.H, config.b, config.R)
            mean = z.mean(axis=1)
            spread = z - mean[:, None, :]
            cov = P.mean(axis=1) + np.einsum("psi,psj->pij", spread, spread) / ns
            width[i, :, week] = np.linalg.det(cov) ** (1.0 / n)
            if week in report:
                summary = summarize(z, P)
                ci_width[i, :, report[week]] = summary.ci_high - summary.ci_low
        if on_interval_done:
            on_interval_done()
    return ScenarioResult(scenario.name, width, ci_width)


def run_study(config: StudyConfig, progress: bool = False) -> StudyResult:
    """Run every scenario; ``progress`` draws a bar on stderr."""
    from tqdm import tqdm

    rng = np.random.default_rng(config.seed)
    total = len(config.scenarios) * len(config.intervals_weeks)
    with tqdm(total=total, desc="frequency study", unit="run", disable=not progress) as bar:
        results = tuple(
            run_scenario(s, config, rng, on_interval_done=lambda: bar.update(1))
            for s in config.scenarios
        )
    return StudyResult(config, results)


def interval_label(interval: int) -> str:
    return "no on-board" if interval == 0 else f"{interval} week" + ("s" if interval > 1 else "")


def percentile_table(result: StudyResult, low: float = 5, high: float = 95) -> dict:
    """``table[report_week][interval_label][scenario][indicator] = [p5, p95]`` of CI widths."""
    table: dict = {}
    for r, week in enumerate(result.config.report_weeks):
        rows = table.setdefault(f"week {week}", {})
        for i, interval in enumerate(result.config.intervals_weeks):
            row = rows.setdefault(interval_label(interval), {})
            for scenario in result.scenarios:
                widths = scenario.ci_width[i, :, r]  # (paths, n)
                q = np.percentile(widths, [low, high], axis=0)
                row[scenario.name] = {
                    name: [round(float(q[0, k]), 4), round(float(q[1, k]), 4)]
                    for k, name in enumerate(INDICATOR_NAMES)
                }
    return table


def format_table(result: StudyResult) -> str:
    """Text table shaped like the paper's Table 2."""
    table = percentile_table(result)
    names = [s.name for s in result.scenarios]
    head = f"{'':10} {'':12}" + "".join(
        f"{name + ' ' + ind:>18}" for name in names for ind in INDICATOR_NAMES
    )
    lines = [
        "95% credible-interval widths in log space, [5th, 95th percentile] across "
        f"{result.config.paths} paths",
        head,
    ]
    for week_label, rows in table.items():
        months = round(int(week_label.split()[1]) / 4.345)
        for j, (label, row) in enumerate(rows.items()):
            first = f"{months} months" if j == 0 else ""
            cells = "".join(
                f"{'[{:.3f},{:.3f}]'.format(*row[name][ind]):>18}"
                for name in names
                for ind in INDICATOR_NAMES
            )
            lines.append(f"{first:10} {label:12}{cells}")
    return "\n".join(lines)


def to_json(result: StudyResult) -> dict:
    """Machine-readable result: the table plus the median W_k curve per scenario and interval."""
    config = result.config
    return {
        "paths": config.paths,
        "weeks": config.weeks,
        "posterior_samples": config.posterior_samples,
        "seed": config.seed,
        "ci_width_log": percentile_table(result),
        "median_width_W": {
            s.name: {
                interval_label(interval): np.round(np.median(s.width[i], axis=0), 6).tolist()
                for i, interval in enumerate(config.intervals_weeks)
            }
            for s in result.scenarios
        },
    }


def plot(result: StudyResult, path: str | Path) -> None:
    """W_k against time per interval, one panel per scenario (like the paper's Fig. 7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    config = result.config
    weeks = np.arange(1, config.weeks + 1)  # W_0 = 0 at the TRC record: off a log axis
    fig, axes = plt.subplots(1, len(result.scenarios), figsize=(5 * len(result.scenarios), 4.2))
    for ax, scenario in zip(np.atleast_1d(axes), result.scenarios, strict=True):
        for i, interval in enumerate(config.intervals_weeks):
            median = np.median(scenario.width[i, :, 1:], axis=0)
            lo, hi = np.percentile(scenario.width[i, :, 1:], [5, 95], axis=0)
            style = dict(color="black", ls="--") if interval == 0 else {}
            (line,) = ax.plot(weeks, median, label=interval_label(interval), **style)
            ax.fill_between(weeks, lo, hi, color=line.get_color(), alpha=0.12, lw=0)
        ax.set_title(f"{scenario.name} degradation")
        ax.set_xlabel("weeks after the TRC record")
        ax.set_ylabel("W = |P|^(1/n)  (log space)")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    np.atleast_1d(axes)[0].legend(title="on-board interval", fontsize=8)
    fig.suptitle(
        f"Width of the credibility zone (Eq. 14): median and 5-95 % band of {config.paths} paths"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(
    config_path: str | Path = DEFAULT_CONFIG,
    *,
    as_json: bool = False,
    plot_path: str | None = None,
    paths: int | None = None,
    seed: int | None = None,
    progress: bool = True,
) -> int:
    """`trackfusion study frequency`: print the table (or JSON), optionally draw the figure."""
    config = load_study_config(config_path, paths=paths, seed=seed)
    result = run_study(config, progress=progress)
    if as_json:
        print(json.dumps(to_json(result), indent=1))
    else:
        print(format_table(result))
    if plot_path:
        plot(result, plot_path)
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion study frequency``: the flags override the study config's values."""
    parser.description = "Monte Carlo of the paper's section 4.2: prints a table like its Table 2."
    parser.add_argument(
        "--config",
        default=str(DEFAULT_CONFIG),
        help="study config (JSON5): scenarios, intervals, sizes (default: %(default)s)",
    )
    parser.add_argument("--paths", type=int, help="Monte Carlo paths per scenario (config's)")
    parser.add_argument("--seed", type=int, help="random seed (config value by default)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    parser.add_argument("--plot", metavar="FILE.png", help="draw W_k against time (like Fig. 7)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")


def run(args: argparse.Namespace) -> int:
    return main(
        args.config,
        as_json=args.json,
        plot_path=args.plot,
        paths=args.paths,
        seed=args.seed,
        progress=not args.no_progress and sys.stderr.isatty(),
    )
