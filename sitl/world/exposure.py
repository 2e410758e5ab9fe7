"""A camera's exposure as it changes over a flight, and its lens's vignetting.

The 8-bit value of a pixel is ``clip(linear * gain(t) * vignette(pixel) + noise, 0, 255)``:
the renderer multiplies its linear image (8-bit levels) by these two factors before the noise
and the quantisation, so a bright patch under a raised gain saturates at 255.

``gain(t) = scene(t) * ae(t)`` (dimensionless, 1 = the idealised renderer's brightness):

- ``scene(t) = drift(t) * cloud(t)``, the light on the ground: a slow sinusoidal drift
  ``1 + drift * sin(2 pi t / drift_period_s + phase)`` and, at Poisson times
  (``clouds_per_min``), the sun behind a cloud for ``cloud_s``: ``1 - cloud_depth * e(t)`` with
  ``e`` rising and falling over ``cloud_ramp_s`` (raised cosine);
- ``ae(t)``, the auto-exposure's gain, piecewise constant: at Poisson times (``steps_per_s``)
  it steps towards what would bring the brightness back to 1 (``1 / scene(t)``), with a
  metering error, each step a brightness change of at most ``step_max`` (0.3 = +-30 %) from
  one frame to the next. Without steps the exposure is fixed and every cloud shows in full.

Deterministic in (seed, time): the random times and draws come from generators seeded by
``(seed, 406..408)`` and are laid out from t = 0 in order, so any frame's gain is the same
whatever frames were asked for before (the threads that render ahead agree).

Vignetting: the natural ``cos^4`` falloff of the ray angle theta off the optical axis, scaled
by ``strength``: ``1 - strength * (1 - cos^4 theta)``; 1 on the axis.
"""

from __future__ import annotations

import math

import numpy as np

from companion.render_options import ExposureOptions
from companion.types import F64

_CHUNK = 256  # events drawn at a time


class ExposureModel:
    """The frame gain ``gain(time_s)`` of one flight (see the module docstring)."""

    def __init__(self, opts: ExposureOptions, seed: int) -> None:
        self.opts = opts
        self._step_rng = np.random.default_rng([seed, 406])
        self._cloud_rng = np.random.default_rng([seed, 407])
        self.drift_phase = float(np.random.default_rng([seed, 408]).uniform(0.0, 2 * math.pi))
        self.step_times_s: list[float] = []
        self.step_gains: list[float] = []  # ae after each step
        self.cloud_starts_s: list[float] = []
        self._ae = 1.0
        self._steps_until = 0.0
        self._clouds_until = 0.0

    # ---------------------------------------------------------------- the light on the ground
    def _cloud_envelope(self, time_s: float) -> float:
        """How much of a cloud is over the sun at ``time_s``: 0..1."""
        o = self.opts
        if o.clouds_per_min <= 0 or o.cloud_depth <= 0:
            return 0.0
        while self._clouds_until <= time_s:
            gaps = self._cloud_rng.exponential(60.0 / o.clouds_per_min, _CHUNK)
            starts = self._clouds_until + np.cumsum(gaps)
            self.cloud_starts_s.extend(float(t) for t in starts)
            self._clouds_until = float(starts[-1])
        ramp = max(o.cloud_ramp_s, 1e-9)
        env = 0.0
        for t0 in self.cloud_starts_s:
            if t0 > time_s:
                break
            dt = time_s - t0
            if dt >= o.cloud_s + ramp:
                continue
            if dt < ramp:
                e = 0.5 - 0.5 * math.cos(math.pi * dt / ramp)
            elif dt < o.cloud_s:
                e = 1.0
            else:
                e = 0.5 + 0.5 * math.cos(math.pi * (dt - o.cloud_s) / ramp)
            env = max(env, e)
        return env

    def scene(self, time_s: float) -> float:
        """The light on the ground at ``time_s`` [s], relative to the idealised renderer's."""
        o = self.opts
        drift = 1.0 + o.drift * math.sin(2 * math.pi * time_s / o.drift_period_s + self.drift_phase)
        return drift * (1.0 - o.cloud_depth * self._cloud_envelope(time_s))

    # ---------------------------------------------------------------- the auto-exposure
    def _lay_steps(self, time_s: float) -> None:
        """Draw the auto-exposure's steps, in time order, up to past ``time_s``."""
        o = self.opts
        hi = math.log1p(o.step_max)
        while self._steps_until <= time_s:
            gaps = self._step_rng.exponential(1.0 / o.steps_per_s, _CHUNK)
            metering = self._step_rng.uniform(-1.0, 1.0, _CHUNK)
            t = self._steps_until
            for gap, err in zip(gaps, metering, strict=True):
                t += float(gap)
                # towards 1 / scene, with a metering error of up to half a step either way
                want = math.log(1.0 / (self.scene(t) * self._ae)) + 0.5 * hi * float(err)
                self._ae *= math.exp(min(max(want, -hi), hi))
                self.step_times_s.append(t)
                self.step_gains.append(self._ae)
            self._steps_until = t

    def auto_exposure(self, time_s: float) -> float:
        """The auto-exposure's gain at ``time_s`` [s] (1 before its first step)."""
        o = self.opts
        if o.steps_per_s <= 0 or o.step_max <= 0:
            return 1.0
        self._lay_steps(time_s)
        k = int(np.searchsorted(np.asarray(self.step_times_s), time_s, side="right"))
        return self.step_gains[k - 1] if k > 0 else 1.0

    def gain(self, time_s: float) -> float:
        """The frame's brightness factor at ``time_s`` [s] (> 0)."""
        return self.scene(time_s) * self.auto_exposure(time_s)


def vignette(rays_cam: F64, strength: float) -> F64:
    """Brightness factor (N,) of unit rays (N, 3) in the camera frame (+z the optical axis):
    ``1 - strength * (1 - cos^4 theta)``, cos theta = the ray's z."""
    cos_theta = np.clip(np.asarray(rays_cam, dtype=np.float64)[:, 2], 0.0, 1.0)
    return np.asarray(1.0 - strength * (1.0 - cos_theta**4), dtype=np.float64)
