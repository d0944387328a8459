"""The in-service fleet of the fast mode: vehicle classes and the units' own sensors.

A railway's fleet mixes vehicle types, and no two sensors are mounted or trimmed alike, so
the on-board indices of one segment differ by train. In the fast mode (``--fidelity
index``) a pass's indices come from the observation model (paper Eq. 3-4) of the unit
that recorded them:

.. math::

    y = H_c z + b_c + \\ln g_u + o_u + e, \\qquad e \\sim N(0, R),

where ``c`` is the train's vehicle class and ``u`` the unit:

* a **vehicle class** (``fleet.classes``: share of the trains, ``H_scale``, ``b_shift``,
  ``speed_factor``) stands for its suspension and wheelbase, which change how track
  geometry reaches the axle box: ``H_c = diag(H_scale) H`` and ``b_c = b + b_shift``
  from the ``index`` section's ``H``, ``b``; its speed profile is the share of the line
  speed its passes run at (``speed_factor``, else the ``index`` section's);
* a **unit** has a gain ``g_u ~ U(1 - gain_spread, 1 + gain_spread)`` on both indices (a
  sensor's sensitivity) and a mounting offset ``o_u ~ N(0, diag(offset_sd^2))`` (log mm
  per indicator: a sensor away from the axle box reads each indicator off by a factor).

In the raw mode (``--fidelity raw``, the bogie physics of ``simulators/bogie.py``) the same
section acts on the physics instead: a class's ``bogie`` entries (``wheelbase_m``,
``vertical_hz``, ``vertical_damping``, ``lateral_hz``, ``lateral_damping``) replace the
defaults of :class:`~simulators.bogie.BogiePhysics` for its trains and its
``speed_factor`` is their cruise speed (share of the line speed); a unit's gain multiplies
every acceleration its sensor measures and its mounting tilt ``N(0, mount_sd_deg^2)``
mixes vertical into lateral (gravity too). The indices then differ by class and unit
through the signal chain itself.

A share ``vertical_only_share`` (default 0) of the units carries a vertical sensor only: in
the raw mode its chunks hold the vertical channels and ``supply_v`` only, in the fast mode
its indices are Top6 only (``indicators: ["top6"]``).

All are drawn from the train and unit ids (:func:`simulators.network.stable_rng`), so a
unit keeps its model for the whole run and across runs with the same seed. The defaults
(one ``standard`` class equal to the ``index`` section, no spread) give every unit the
same model.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from simulators.bogie import BogiePhysics
from simulators.index_model import IndexSensorModel
from simulators.network import stable_rng
from simulators.train import TrainConfig
from simulators.truth import config_pair

BOGIE_FIELDS = {"wheelbase_m", "vertical_hz", "vertical_damping", "lateral_hz", "lateral_damping"}
assert {f.name for f in dataclasses.fields(BogiePhysics)} >= BOGIE_FIELDS

MIXED = {  # `--fleet mixed` of bench.correctness: three vehicle types, sensors within ±10 %
    "classes": {
        "emu": {"share": 0.5, "H_scale": [1.0, 1.0], "b_shift": [0.0, 0.0]},
        "loco_hauled": {
            "share": 0.3,
            "H_scale": [1.1, 0.85],
            "b_shift": [0.12, -0.08],
            "speed_factor": [0.6, 0.8],
            "bogie": {"wheelbase_m": 2.8, "vertical_hz": 6.0, "vertical_damping": 0.25},
        },
        "dmu": {
            "share": 0.2,
            "H_scale": [0.9, 1.1],
            "b_shift": [-0.1, 0.1],
            "speed_factor": [0.7, 0.9],
            "bogie": {"wheelbase_m": 2.3, "vertical_hz": 9.0, "lateral_hz": 5.0},
        },
    },
    "gain_spread": 0.1,
    "offset_sd": [0.05, 0.08],
    "mount_sd_deg": 2.0,
}


@dataclass(frozen=True)
class VehicleClass:
    name: str
    share: float
    H_scale: np.ndarray  # (2,)
    b_shift: np.ndarray  # (2,) log mm
    speed_factor: tuple[float, float]
    bogie: Mapping[str, float]  # raw mode: BogiePhysics fields of this class
    cruise_factor: tuple[float, float] | None  # raw mode: its own speed_factor, if given


@dataclass(frozen=True)
class Unit:
    """One on-board unit: its train's class, its sensor, and the model its indices follow."""

    train: str
    unit: str
    vehicle_class: str
    gain: float
    offset: np.ndarray  # (2,) log mm
    model: IndexSensorModel  # y = H z + b + e with the class and the sensor in H and b
    speed_factor: tuple[float, float]
    mount_rad: float  # raw mode: the sensor's tilt about the running axis
    vertical_only: bool = False  # a vertical sensor only: Top6 indices, vertical channels


class Fleet:
    """Vehicle classes and unit sensors of the ``fleet`` section (see the module text)."""

    def __init__(
        self,
        base: IndexSensorModel,
        classes: list[VehicleClass],
        gain_spread: float,
        offset_sd: np.ndarray,
        seed: int,
        mount_sd_deg: float = 0.0,
        vertical_only_share: float = 0.0,
    ) -> None:
        if not classes or sum(c.share for c in classes) <= 0:
            raise ValueError("fleet.classes: at least one class with a share > 0")
        if not 0 <= gain_spread < 1 or (offset_sd < 0).any() or offset_sd.shape != (2,):
            raise ValueError("fleet: gain_spread in [0, 1), offset_sd two values >= 0")
        self.base, self.classes, self.seed = base, classes, int(seed)
        self.gain_spread, self.offset_sd = float(gain_spread), offset_sd
        if not mount_sd_deg >= 0:
            raise ValueError(f"fleet.mount_sd_deg: must be >= 0, got {mount_sd_deg}")
        self.mount_sd_rad = np.deg2rad(mount_sd_deg)
        if not 0 <= vertical_only_share <= 1:
            raise ValueError(f"fleet.vertical_only_share: in [0, 1], got {vertical_only_share}")
        self.vertical_only_share = float(vertical_only_share)
        shares = np.array([c.share for c in classes], dtype=np.float64)
        self._cum = np.cumsum(shares / shares.sum())

    @classmethod
    def from_config(cls, config: Mapping, seed: int) -> Fleet:
        """From the simulator config's ``index`` and (optional) ``fleet`` sections."""
        base = IndexSensorModel.from_config(config)
        sec = config.get("fleet") or {}
        default_speed = config_pair(config["index"], "speed_factor", "index")
        raw = sec.get("classes") or {"standard": {"share": 1.0}}
        classes = []
        for name, c in raw.items():
            where = f"fleet.classes.{name}"
            h = np.asarray(c.get("H_scale", [1.0, 1.0]), dtype=np.float64)
            b = np.asarray(c.get("b_shift", [0.0, 0.0]), dtype=np.float64)
            share = float(c.get("share", 0.0))
            if h.shape != (2,) or b.shape != (2,) or (h <= 0).any() or share < 0:
                raise ValueError(f"{where}: H_scale two values > 0, b_shift two, share >= 0")
            speed = config_pair(c, "speed_factor", where) if "speed_factor" in c else default_speed
            bogie = {k: float(v) for k, v in (c.get("bogie") or {}).items()}
            unknown = set(bogie) - BOGIE_FIELDS
            if unknown:
                raise ValueError(
                    f"{where}.bogie: unknown {sorted(unknown)}; known {sorted(BOGIE_FIELDS)}"
                )
            own_speed = speed if "speed_factor" in c else None
            classes.append(VehicleClass(name, share, h, b, speed, bogie, own_speed))
        offset = np.asarray(sec.get("offset_sd", [0.0, 0.0]), dtype=np.float64)
        gain = float(sec.get("gain_spread", 0.0))
        return cls(
            base,
            classes,
            gain,
            offset,
            seed,
            float(sec.get("mount_sd_deg", 0.0)),
            float(sec.get("vertical_only_share", 0.0)),
        )

    def vehicle_class(self, train: str) -> VehicleClass:
        """The class of ``train`` (drawn once per train id by the class shares)."""
        u = stable_rng(self.seed, "fleet-class", train).random()
        return self.classes[
            min(int(np.searchsorted(self._cum, u, side="right")), len(self._cum) - 1)
        ]

    def unit(self, train: str, unit: str) -> Unit:
        """The model of ``unit`` on ``train`` (same ids, same model)."""
        klass = self.vehicle_class(train)
        rng = stable_rng(self.seed, "fleet-unit", train, unit)
        gain = float(1.0 + rng.uniform(-self.gain_spread, self.gain_spread))
        offset = rng.standard_normal(2) * self.offset_sd
        mount = float(rng.standard_normal() * self.mount_sd_rad)
        H = klass.H_scale[:, None] * self.base.H
        b = self.base.b + klass.b_shift + np.log(gain) + offset
        model = IndexSensorModel(H, b, self.base.R)
        # its own stream: the share leaves every other draw of the unit as it is
        vertical = stable_rng(self.seed, "fleet-sensor", train, unit).random()
        return Unit(
            train,
            unit,
            klass.name,
            gain,
            offset,
            model,
            klass.speed_factor,
            mount,
            vertical < self.vertical_only_share,
        )

    def train_config(self, train: str, base: TrainConfig | None = None) -> TrainConfig:
        """Raw mode: the train's constants with its class's bogie and cruise speed."""
        base = base or TrainConfig()
        klass = self.vehicle_class(train)
        physics = dataclasses.replace(base.physics, **klass.bogie)
        cruise = klass.cruise_factor or base.cruise_factor
        return dataclasses.replace(base, physics=physics, cruise_factor=cruise)
