"""One on-board unit on a bogie: track profile -> suspension -> MEMS accelerometers -> ADC.

Per chunk of sample times (2000 Hz) and the bogie's kinematics, ``BogieUnit`` returns
``(n, 7)`` float32 samples in the order ``ACCEL_CHANNELS + (SUPPLY_CHANNEL,)``: left and
right accelerometers (z vertical up, y lateral to the vehicle's left, x longitudinal to
the vehicle's end A) in g, then the supply voltage in V. The chain, in order:

1. Input: the bogie frame follows the mean of the profile under its two wheelsets
   (``s +- wheelbase/2``; wheelbase averaging). Vertical per rail; lateral is one rigid
   frame motion: the mean of the two rails' alignment (the wheelset is guided by both),
   plus roll from the cross-level difference (``roll_coupling``) and kinematic hunting
   (a narrowband lateral sway at ``hunting_wavelength_m`` of travelled distance; this
   is why Align10 comes out noisier than Top6, as in the paper, section 3.2).
2. Suspension per axis, from track displacement (mm) to frame acceleration (g):

   .. math::

       H(s) = \\frac{s^2 (2\\zeta\\omega s + \\omega^2)}{s^2 + 2\\zeta\\omega s + \\omega^2}
              \\cdot \\frac{\\omega_a^2}{s^2 + \\sqrt{2}\\,\\omega_a s + \\omega_a^2}
              \\cdot \\frac{1}{9806.65}

   a base-excited oscillator (natural frequency ``omega``, damping ``zeta``) times the
   sensor's 2-pole Butterworth bandwidth ``omega_a``, which also makes ``H`` proper;
   discretised by the bilinear transform and run as second-order sections with the
   filter state carried across chunks, so chunk boundaries are seamless.
3. Impulses at rail joints and welds, when either wheelset crosses one: a decaying
   ``impulse_hz`` oscillation of peak ``impulse_g * gain * v / impulse_ref_mps`` on both
   sides (vertical; ``impulse_lateral`` of it laterally), filter state carried as well.
4. Mapping to the vehicle: on the outbound (``direction = +1``) the vehicle's left is the
   track's left rail; after turning back the vehicle runs end B first, so its left side
   is over the track's right rail and y and x change sign. ``z`` reads +1 g at rest
   (specific force: the sensor reports gravity; the extraction's band-pass removes it).
   ``x`` is ``direction * dv/dt / g``.
5. Per-chunk artefacts (random, seeded by ``(seed, crc32(train), unit, seq)``): MEMS white
   noise of ``noise_density_g`` per sqrt(Hz), i.e. ``sigma = density * sqrt(fs / 2)`` per
   sample; bursts of outliers on ONE side's z and y, all bursts of a chunk on the same
   side, so the two rails are never hit at once (the reason for min(left, right));
   supply sags. Bursts, sags and flatlines end at the chunk's end at the latest.
6. Ratiometric sensor: every accelerometer output is multiplied by ``V / supply_v``
   (ingestion corrects by ``supply_v / V`` using the supply channel); then clipped at
   ``+-clip_g``; then dropouts: a channel flatlines (zeros or a held value) for a while.
   A chunk may also be lost whole (``dropped``): it is still computed so the state stays
   continuous, and the gateway skips publishing it.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import fft, signal

from simulators.profile import LineProfile

G_MMPS2 = 9806.65  # standard gravity in mm/s^2
_HUNT_TAG, _SUPPLY_TAG = 0x48554E54, 0x53555050  # "HUNT", "SUPP": per-unit fixed streams


@dataclass(frozen=True)
class BogiePhysics:
    """Physics and sensor constants of a bogie unit (``simulator.json5`` of services/defaults/
    may override).

    Rates are per second of running time; durations are ``(min, max)`` in seconds.
    """

    fs_hz: float = 2000.0  # sampling rate
    wheelbase_m: float = 2.5
    vertical_hz: float = 8.0  # primary suspension, vertical natural frequency
    vertical_damping: float = 0.3
    lateral_hz: float = 4.5
    lateral_damping: float = 0.25
    sensor_bandwidth_hz: float = 400.0  # MEMS anti-alias, 2-pole Butterworth
    roll_coupling: float = 0.25  # lateral mm at the sensor per mm of half cross-level
    hunting_mm: float = 0.6  # rms lateral sway; makes Align10 noisier than Top6 (paper 3.2)
    hunting_wavelength_m: float = 16.0  # Klingel wavelength of the worn wheel profile
    noise_density_g: float = 300e-6  # MEMS noise, g/sqrt(Hz)
    clip_g: float = 16.0  # full scale
    impulse_g: float = 1.0  # peak at a joint (gain 1) at impulse_ref_mps
    impulse_ref_mps: float = 20.0
    impulse_hz: float = 60.0
    impulse_decay_s: float = 0.015
    impulse_lateral: float = 0.3
    outlier_rate_hz: float = 0.01  # one-side bursts
    outlier_g: float = 1.0  # rms of a burst
    outlier_s: tuple[float, float] = (0.05, 0.4)
    flatline_rate_hz: float = 0.002  # one channel stuck at 0 or at a held value
    flatline_s: tuple[float, float] = (0.05, 1.0)
    missing_chunk_prob: float = 0.001  # a whole chunk lost (not published)
    supply_v: float = 5.0  # nominal supply, the ratiometric reference
    supply_fluct: float = 0.02  # amplitude of each of 3 slow sinusoids (20-600 s periods)
    supply_noise_v: float = 0.002
    sag_rate_hz: float = 0.002
    sag_depth: float = 0.15  # relative, at most
    sag_s: tuple[float, float] = (0.05, 0.3)


class Kinematics(NamedTuple):
    """Where a bogie is at each sample: arrays of shape (n,)."""

    t: np.ndarray  # epoch s
    chainage_m: np.ndarray  # bogie centre
    speed_mps: np.ndarray  # >= 0
    accel_mps2: np.ndarray  # dv/dt along the direction of travel
    direction: np.ndarray  # +1 chainage increasing (end A leading), -1 decreasing
    odometer_m: np.ndarray  # distance travelled, monotonic


def _suspension_sos(f_hz: float, zeta: float, phys: BogiePhysics) -> np.ndarray:
    w, wa = 2 * np.pi * f_hz, 2 * np.pi * phys.sensor_bandwidth_hz
    zeros = np.array([0.0, 0.0, -w / (2 * zeta)])
    poles = np.r_[np.roots([1, 2 * zeta * w, w * w]), np.roots([1, np.sqrt(2) * wa, wa * wa])]
    z, p, k = signal.bilinear_zpk(zeros, poles, 2 * zeta * w * wa * wa / G_MMPS2, phys.fs_hz)
    return signal.zpk2sos(z, p, k)


class BogieUnit:
    """The stateful signal chain of one unit; call ``chunk`` with consecutive chunks.

    Parameters
    ----------
    profile : LineProfile
        The line the unit runs on.
    physics : BogiePhysics
        Constants.
    seed : int
        World seed.
    train_id : str
        Stable train id (seeds the random streams).
    unit_no : int
        Unit number on the train.
    gain : float
        The sensor's sensitivity relative to nominal (1: exact); multiplies what it measures.
    mount_rad : float
        The sensor's mounting tilt about the running axis: it reads
        ``y' = y cos a + z sin a``, ``z' = z cos a - y sin a`` of the true lateral ``y`` and
        vertical ``z`` (gravity included), per side.
    """

    def __init__(
        self,
        profile: LineProfile,
        physics: BogiePhysics,
        seed: int,
        train_id: str,
        unit_no: int,
        *,
        gain: float = 1.0,
        mount_rad: float = 0.0,
    ) -> None:
        self.profile, self.phys = profile, physics
        self.gain, self.mount_rad = float(gain), float(mount_rad)
        self._key = [seed, zlib.crc32(train_id.encode()), unit_no]
        ph = physics
        self._sos_v = _suspension_sos(ph.vertical_hz, ph.vertical_damping, ph)
        self._sos_l = _suspension_sos(ph.lateral_hz, ph.lateral_damping, ph)
        # Impulse response r^n sin(w0 n): a resonator, normalised to a peak of 1.
        r, w0 = np.exp(-1.0 / (ph.impulse_decay_s * ph.fs_hz)), 2 * np.pi * ph.impulse_hz / ph.fs_hz
        self._imp_a = np.array([1.0, -2 * r * np.cos(w0), r * r])
        h = signal.lfilter([0.0, 1.0], self._imp_a, np.r_[1.0, np.zeros(int(ph.fs_hz // 10))])
        self._imp_b = np.array([0.0, 1.0 / np.abs(h).max()])
        self._hunt = self._hunting_table()
        rng = np.random.default_rng([*self._key, _SUPPLY_TAG])
        self._supply_w = 2 * np.pi / rng.uniform(20.0, 600.0, 3)
        self._supply_phase = rng.uniform(0.0, 2 * np.pi, 3)
        self.reset()

    def reset(self) -> None:
        """Forget the filter states (the next chunk starts in steady state)."""
        self._zi_v = self._zi_l = self._zi_imp = self._joint_count = None

    def _hunting_table(self) -> np.ndarray:
        """A periodic narrowband lateral sway over distance, rms ``hunting_mm``, 0.25 m grid."""
        n, dx = 16384, 0.25
        f = fft.rfftfreq(n, dx)
        f0 = 1.0 / self.phys.hunting_wavelength_m
        amp = np.exp(-0.5 * ((f - f0) / (0.1 * f0)) ** 2)
        rng = np.random.default_rng([*self._key, _HUNT_TAG])
        x = fft.irfft(amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)), n)
        return x * (self.phys.hunting_mm / x.std())

    def dynamics(self, kin: Kinematics) -> np.ndarray:
        """Clean accelerations in the vehicle frame (g), ``ACCEL_CHANNELS`` order, shape (6, n).

        Stateful: consecutive calls continue one another exactly.
        """
        ph, n = self.phys, kin.t.size
        s = kin.chainage_m
        half = 0.5 * ph.wheelbase_m
        under = self.profile.sample(np.stack([s - half, s + half]))  # (4, 2, n)
        p = under.mean(axis=1)  # wheelbase averaging
        u = (kin.odometer_m / 0.25) % self._hunt.size
        i = u.astype(np.intp)
        hunt = self._hunt[i] + (u - i) * (self._hunt[(i + 1) % self._hunt.size] - self._hunt[i])
        lat_in = 0.5 * (p[2] + p[3]) + ph.roll_coupling * 0.5 * (p[0] - p[1]) + hunt
        vin, lin = p[:2], lat_in[None]
        if self._zi_v is None:  # start in steady state: no start-up transient
            self._zi_v = signal.sosfilt_zi(self._sos_v)[:, None, :] * vin[None, :, :1]
            self._zi_l = signal.sosfilt_zi(self._sos_l)[:, None, :] * lin[None, :, :1]
            self._zi_imp = np.zeros(2)
        av, self._zi_v = signal.sosfilt(self._sos_v, vin, axis=-1, zi=self._zi_v)
        al, self._zi_l = signal.sosfilt(self._sos_l, lin, axis=-1, zi=self._zi_l)
        imp, self._zi_imp = signal.lfilter(
            self._imp_b, self._imp_a, self._joint_impulses(s, kin.speed_mps, half), zi=self._zi_imp
        )
        vl, vr, lat = av[0] + imp, av[1] + imp, al[0] + ph.impulse_lateral * imp
        fwd = kin.direction > 0
        sgn = np.where(fwd, 1.0, -1.0)
        out = np.empty((6, n))
        out[0], out[3] = np.where(fwd, vl, vr) + 1.0, np.where(fwd, vr, vl) + 1.0
        out[1] = out[4] = sgn * lat
        out[2] = out[5] = kin.direction * kin.accel_mps2 * (1000.0 / G_MMPS2)
        return out

    def _joint_impulses(self, s: np.ndarray, v: np.ndarray, half: float) -> np.ndarray:
        """Impulse train: amplitude at the sample where a wheelset crosses a joint or weld."""
        joints, gain = self.profile.joints_m, self.profile.joint_gain
        counts = np.searchsorted(joints, np.stack([s - half, s + half]))  # (2, n)
        prev = counts[:, :1] if self._joint_count is None else self._joint_count
        self._joint_count = counts[:, -1:]
        k = np.diff(np.concatenate([prev, counts], axis=1), axis=1)  # +-1 at a crossing
        w, i = np.nonzero(k)
        j = np.minimum(counts[w, i], counts[w, i] - k[w, i])  # the joint crossed
        out = np.zeros(s.size)
        np.add.at(out, i, self.phys.impulse_g * gain[j] * v[i] / self.phys.impulse_ref_mps)
        return out

    def supply(self, t: np.ndarray) -> np.ndarray:
        """Slow supply fluctuation (V) without sags and noise: a fixed function of time."""
        ph = self.phys
        wave = np.sin(np.outer(t, self._supply_w) + self._supply_phase).sum(axis=1)
        return ph.supply_v * (1.0 + 0.5 * ph.supply_fluct * wave)

    def chunk(self, seq: int, kin: Kinematics) -> tuple[np.ndarray, bool]:
        """Samples of chunk ``seq``: ``(n, 7)`` float32 in g and V, and the dropped flag.

        Call with consecutive chunks (the suspension and impulse filters carry state).
        """
        ph, n = self.phys, kin.t.size
        acc = self.dynamics(kin)
        if self.mount_rad:
            c, s = np.cos(self.mount_rad), np.sin(self.mount_rad)
            for z, y in ((0, 1), (3, 4)):  # (vertical, lateral) rows of each side
                acc[y], acc[z] = c * acc[y] + s * acc[z], c * acc[z] - s * acc[y]
        rng = np.random.default_rng([*self._key, seq])
        dropped = bool(rng.random() < ph.missing_chunk_prob)
        acc += rng.standard_normal((6, n)) * (ph.noise_density_g * np.sqrt(ph.fs_hz / 2))
        span = n / ph.fs_hz
        side = int(rng.integers(2))  # one side per chunk: never both rails at once
        for _ in range(rng.poisson(ph.outlier_rate_hz * span)):
            _, i0, i1 = self._burst(rng, n, ph.outlier_s)
            acc[3 * side : 3 * side + 2, i0:i1] += rng.normal(0.0, ph.outlier_g, (2, i1 - i0))
        volts = self.supply(kin.t) + rng.normal(0.0, ph.supply_noise_v, n)
        for _ in range(rng.poisson(ph.sag_rate_hz * span)):
            _, i0, i1 = self._burst(rng, n, ph.sag_s)
            volts[i0:i1] *= 1.0 - ph.sag_depth * rng.uniform(0.3, 1.0)
        acc *= self.gain * volts / ph.supply_v  # sensitivity, ratiometric output
        np.clip(acc, -ph.clip_g, ph.clip_g, out=acc)
        for _ in range(rng.poisson(ph.flatline_rate_hz * span)):
            _, i0, i1 = self._burst(rng, n, ph.flatline_s)
            c = rng.integers(6)
            acc[c, i0:i1] = 0.0 if rng.random() < 0.5 else acc[c, i0]
        out = np.empty((n, 7), dtype=np.float32)
        out[:, :6] = acc.T
        out[:, 6] = volts
        return out, dropped

    def _burst(self, rng: np.random.Generator, n: int, dur_s: tuple[float, float]):
        """A random (side, start, stop) inside the chunk; bursts end at the chunk's end."""
        side = int(rng.integers(2))
        i0 = int(rng.integers(n))
        return side, i0, min(n, i0 + int(rng.uniform(*dur_s) * self.phys.fs_hz))
