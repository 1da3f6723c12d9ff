"""Fast B-mode frame synthesis for wire phantoms and printed objects (design §4 "Image formation").

The model works in linear echo amplitude on the pixel grid of a probe (linear, or convex: then
each echo turns with its beam and the fan is dark outside); amplitude
1.0 just saturates the display. Levels are in dB re that amplitude.

1. Wire dots. The point-spread function (``core.twin.imaging.dot_amplitude``) has a Gaussian main lobe with
   faint side lobes laterally, and axially a sharp Gaussian top edge with a short exponential tail
   below it. The tail is narrower than the main lobe. The whole echo follows a "smile" arc whose
   ends bend toward the probe. The core sigmas are solved so that the *displayed* widths (at half
   the maximum gray level of the 8-bit image) follow ``ImagingModel``: lateral FWHM 0.7 mm at
   15 mm depth growing to 2 mm at 35 mm, axial FWHM 0.7 mm. The main lobe peaks on the wire (the
   given pixel (u, v)), as a pulse echo does; the tail and the smile then pull every centroid
   off it by an amount that changes with depth, which the segmentation must live with, as on a
   real bench.

   With an elevational slice (``ImagingModel.elevation_fwhm_mm`` > 0, the ``bench`` scanner) a
   wire echoes from every elevation inside the slice: given its direction in the image frame,
   the dot is the sum of PSFs along the wire's in-plane shift, weighted by the slice's profile,
   with random phases for a rough wire and from random points of its cross-section for a wire
   of some diameter. A wire tilted toward the beam echoes weaker and longer, and rings down
   below itself.
2. Noise, by level (``core.twin.imaging.NoiseModel``):
   - Rayleigh speckle from precomputed correlated textures, cropped and flipped at random per
     frame;
   - near-field reverberation bands under the probe face;
   - drifting particles;
   - per-dot amplitude jitter and texture;
   - at ``harsh``, bubbles, some of them with comet tails.
3. Specular reflectors. An optional object surface (one sub-pixel row per column) and the tank
   bottom each give a bright line and shadow what lies below it. The tank bottom also rings
   briefly and echoes again at twice its depth.
4. Attenuation and time-gain compensation (TGC) as a per-row gain. The TGC nominally cancels the
   attenuation, and the noise model perturbs it smoothly per frame.
5. Log compression over ``dynamic_range_db`` below saturation, then a power-law gray map. This
   comes last, as in a scanner.

Frames: pixel (u, v) = (column, row). Depth in mm is ``v * sy``, where ``sy`` is the probe's
*true* axial spacing (the medium's sound speed). Lateral position in mm is ``u * sx``.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from probecal.core.geometry.probe import Probe
from probecal.core.io.limits import checked_bytes
from probecal.core.twin.imaging import (
    BENCH_IMAGING,
    NOISE_LEVELS,
    ImagingModel,
    NoiseModel,
    Psf,
    axial_profile,
    axial_sigma_mm,
    dot_amplitude,
    dot_amplitude_at,
    lateral_sigma_mm,
)

DB = 20.0 / np.log(10.0)  # dB per neper of amplitude
TEXTURE_PAD = 64  # speckle textures are this many pixels larger than the frame in each direction
MAX_SMEAR = 5.0  # in-plane shift (mm) per mm of elevation beyond which a wire counts as in-plane
WIRE_GRAIN_MM = 0.2  # a rough wire's scatterers lie this far apart along it (about a wavelength)
GRAIN_TABLE = 1 << 16  # grains drawn per renderer; positions along the wires wrap around after this many
TEXTURE_SIGMA_PX = 16.0  # a speckle texture is drawn on a grid coarse enough that its blur spans this many cells
ECHO_BATCH = 1 << 19  # echo samples x patch pixels computed at once: a dot's working arrays stay a few MB


IMAGING_BYTES_PER_PIXEL = 112
"""The most memory the twin's scanner holds per pixel of its frames, :data:`TEXTURE_PAD` larger
each way (measured 56-97 bytes: about 60 while speckle textures are drawn at full resolution, their
float64 noise and float32 blurs; 97 at 0.001 mm/px, where one dot's patch is the whole frame)."""


def check_imaging(probe: Probe, source: str | Path | None = None) -> int:
    """The bytes imaging ``probe``'s frames takes (:data:`IMAGING_BYTES_PER_PIXEL`); InputError
    naming ``source`` when that passes the memory limit, before any of it is taken."""
    return checked_bytes(source, f"imaging frames of {probe.width_px} x {probe.height_px} px",
                         (probe.height_px + TEXTURE_PAD, probe.width_px + TEXTURE_PAD), IMAGING_BYTES_PER_PIXEL)


def _blur_1d(values: np.ndarray, sigma: float, border: int) -> np.ndarray:
    """Gaussian blur (sigma in samples) of a 1-D profile, as float32."""
    k = 2 * int(np.ceil(3 * sigma)) + 1
    row = np.asarray(values, dtype=np.float32)[None, :]
    return cv2.GaussianBlur(row, (k, 1), sigmaX=sigma, borderType=border)[0]


class BModeRenderer:
    """Synthesises uint8 B-mode frames for one probe and noise level.

    The constructor precomputes the per-depth PSF table (2 mm steps), the speckle textures, the
    reverberation bands and the gray map (about 0.1 s). ``render`` then costs a few full-frame
    array operations plus one small patch per echo.
    """

    n_textures = 4

    def __init__(
        self,
        probe: Probe,
        noise: str | NoiseModel = "realistic",
        seed: int | None = 0,
        imaging: ImagingModel | None = None,
    ):
        check_imaging(probe)
        self.probe = probe
        self.noise = NOISE_LEVELS[noise] if isinstance(noise, str) else noise
        if imaging is None:  # the named level's own scanner
            imaging = BENCH_IMAGING if noise == "bench" else ImagingModel()
        self.imaging = imaging
        self.sx, self.sy = probe.true_spacing_mm
        self.shape = (probe.height_px, probe.width_px)
        h, w = self.shape
        seeds = np.random.SeedSequence(seed).spawn(2)
        fixed_rng, self._rng = (np.random.default_rng(s) for s in seeds)
        self._start = probe.true_start_depth_mm  # the first row's depth below the face (mm)
        self._depth = self._start + np.arange(h) * self.sy
        self._base_gain_db = (imaging.tgc_db_per_mm - imaging.attenuation_db_per_mm) * self._depth
        levels = np.arange(256) / 255.0
        self._gray_lut = np.round(255.0 * levels**imaging.gray_gamma).astype(np.uint8)
        self._log_scale = 255.0 * DB / imaging.dynamic_range_db
        self._floor = 10 ** ((-imaging.dynamic_range_db - 20.0) / 20)
        self._sigma_z = axial_sigma_mm(imaging)
        self._table_depth = np.arange(0.0, self._start + h * self.sy + 2.5, 2.0)
        fwhm = imaging.lateral_fwhm_mm(self._table_depth)
        self._table_sigma_x = np.array([lateral_sigma_mm(f, self._sigma_z, imaging) for f in fwhm])
        textured = np.isfinite(self.noise.speckle_db) or self.noise.dot_texture > 0
        self._textures = self._make_textures(fixed_rng) if textured else []
        self._reverb = self._make_reverb(fixed_rng)
        unevenness = self.noise.tank_unevenness_mm / self.sy
        self._tank_rows = unevenness * self._smooth_noise(fixed_rng, w, 6.0 / self.sx)
        mottle = self.noise.tank_mottle_db * self._smooth_noise(fixed_rng, w, 4.0 / self.sx)
        self._tank_gain = (10 ** (mottle / 20)).astype(np.float32)
        self._grains = fixed_rng.random((GRAIN_TABLE, 3))  # per grain: phase, radius, angle (0..1)
        fan = probe.fan
        self._outside_fan = None if fan is None else ~fan.mask(w, h)  # a fan image is black outside it

    # --- precomputation --------------------------------------------------------------------------

    def psf(self, depth_mm: float) -> Psf:
        """The dot PSF at a depth (mm)."""
        im = self.imaging
        sigma_x = float(np.interp(depth_mm, self._table_depth, self._table_sigma_x))
        floor_db = -im.dynamic_range_db - im.dot_db - 3.0  # below the display, re the dot peak
        main = np.sqrt(-2 * floor_db / DB)
        side = im.sidelobe_width * np.sqrt(2 * max(im.sidelobe_db - floor_db, 0.0) / DB)
        half_x = sigma_x * max(main, side)
        spread = self._sigma_z * main
        rise = im.smile_per_mm * half_x**2
        tail = im.tail_length_mm * (im.tail_db - floor_db) / DB
        return Psf(sigma_x, self._sigma_z, half_x, rise + spread, max(tail, spread))

    def _make_textures(self, rng: np.random.Generator) -> list[np.ndarray]:
        """Unit-mean Rayleigh envelopes, TEXTURE_PAD px larger than the frame, PSF-correlated."""
        h, w = self.shape
        sig_x = max(0.45 * self.psf(25.0).sigma_x / self.sx, 0.5)
        sig_z = max(0.6 * self._sigma_z / self.sy, 0.5)
        # A field correlated over many pixels (a fine spacing) is drawn on a coarser grid and
        # interpolated: a blur's cost grows with its width, and at 0.001 mm/px it spans hundreds.
        step_x, step_z = (max(1, int(sigma // TEXTURE_SIGMA_PX)) for sigma in (sig_x, sig_z))
        size = (w + TEXTURE_PAD, h + TEXTURE_PAD)
        coarse = (step_x, step_z) != (1, 1)
        drawn = (-(-size[1] // step_z) + int(coarse), -(-size[0] // step_x) + int(coarse))  # rows, columns
        out = []
        for _ in range(self.n_textures):
            iq = rng.standard_normal((2, *drawn)).astype(np.float32)
            i, q = (cv2.GaussianBlur(c, (0, 0), sigmaX=sig_x / step_x, sigmaY=sig_z / step_z) for c in iq)
            if coarse:
                i, q = (cv2.resize(c, size, interpolation=cv2.INTER_LINEAR) for c in (i, q))
            env = cv2.magnitude(i, q)
            out.append(env / env.mean())
        return out

    def _make_reverb(self, rng: np.random.Generator) -> np.ndarray:
        """Near-field reverberation (rows x width): bands every 1.1 mm below the face, 8 dB weaker
        per bounce (arcs under a convex face)."""
        h, w = self.shape
        if self.probe.fan is None:
            z = self._depth[self._depth < 8.0][:, None]
        else:
            z = np.asarray(self.probe.beam_at(np.arange(w)[None, :], np.arange(h)[:, None])[1])
            z = z[: int(np.argmax(z.min(axis=1) >= 8.0)) or h]
        period, decay_db = 1.1, 8.0
        bands = sum(
            10 ** (-decay_db * k / 20)
            * np.exp(-0.5 * ((z - k * period - 0.3) / (1.2 * self._sigma_z)) ** 2)
            for k in range(int(8.0 / period))
        )
        lateral = 1.0 + 0.3 * self._smooth_noise(rng, w, 3.0 / self.sx)
        return (bands * lateral[None, :]).astype(np.float32)

    @staticmethod
    def _smooth_noise(rng: np.random.Generator, n: int, scale_px: float) -> np.ndarray:
        """A smooth zero-mean random profile: n samples, peak magnitude 1, correlated ~scale_px."""
        raw = rng.standard_normal((1, n)).astype(np.float32)
        smooth = _blur_1d(raw[0], max(scale_px, 0.5), cv2.BORDER_REFLECT)
        smooth -= smooth.mean()
        return smooth / max(float(np.abs(smooth).max()), 1e-9)

    # --- echoes ----------------------------------------------------------------------------------

    def _dot_patch(self, z_px: np.ndarray, x_px: np.ndarray, psf: Psf) -> np.ndarray:
        """Dot PSF on a grid of row / column offsets (px) from the wire centre (batched as
        :func:`dot_amplitude`), along the PSF's beam."""
        x, z = x_px * self.sx, z_px * self.sy
        if not psf.beam_rad:
            return dot_amplitude(x, z, psf.sigma_x, psf.sigma_z, self.imaging)
        lateral, axial = _beam_axes(x[..., None, :], z[..., :, None], psf.beam_rad)
        return dot_amplitude_at(lateral, axial, psf.sigma_x, psf.sigma_z, self.imaging)

    def _window(
        self, u: float, v: float, half_x: float, above: float, below: float
    ) -> tuple[int, int, int, int] | None:
        """Pixel window (r0, r1, c0, c1) around (u, v), extents in mm, clipped; None if empty."""
        h, w = self.shape
        r0 = max(int(np.floor(v - above / self.sy)), 0)
        r1 = min(int(np.ceil(v + below / self.sy)) + 1, h)
        c0 = max(int(np.floor(u - half_x / self.sx)), 0)
        c1 = min(int(np.ceil(u + half_x / self.sx)) + 1, w)
        return (r0, r1, c0, c1) if r0 < r1 and c0 < c1 else None

    def _slice_samples(
        self, depth_mm: float, smear_px: np.ndarray | None, grain_at: tuple[float, float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Where an oblique wire echoes across the elevational slice: (K, 2) offsets (px) from its
        crossing, (K,) weights summing to 1 (the slice's two-way Gaussian profile), and (K, 3) draws
        in 0..1 of each echo's grain (phase, then radius and angle on the wire's cross-section).

        ``smear_px``: the wire's in-plane shift (px) per mm of elevation; None: along the normal.
        ``grain_at``: the crossing's position along the phantom's wires laid end to end (mm) and
        the wire's elevation per mm along it. The echoes then come from the wire's own grains,
        fixed along it every :data:`WIRE_GRAIN_MM`, so a crossing that moves little echoes
        alike from frame to frame; None: evenly spaced echoes whose grains the caller draws anew
        (None returned).
        A wire with a diameter echoes from at least 9 elevations even along the normal, each from
        its own point of the cross-section (see :meth:`_add_dot`).
        """
        fwhm = self.imaging.elevation_fwhm_at(depth_mm)
        reach = 2.0 * fwhm / 2.3548  # two sigmas of the slice profile (mm)
        thick = self.imaging.wire_diameter_mm > 0
        smear = np.zeros(2) if smear_px is None else np.asarray(smear_px, float)
        length = 2.0 * reach * float(np.hypot(*smear))  # px
        if reach <= 0 or (length < 0.25 and not thick):
            grains = None if grain_at is None else self._grain(np.array([grain_at[0]]))
            return np.zeros((1, 2)), np.ones(1), grains
        if grain_at is None:
            n = int(np.clip(np.ceil(length / 0.5), 9 if thick else 3, 41)) | 1
            e = np.linspace(-reach, reach, n)
            grains = None
        else:
            along, rise = grain_at[0], float(np.copysign(max(abs(grain_at[1]), 1.0 / MAX_SMEAR), grain_at[1]))
            s = np.arange(np.ceil((along - reach / abs(rise)) / WIRE_GRAIN_MM),
                          np.floor((along + reach / abs(rise)) / WIRE_GRAIN_MM) + 1) * WIRE_GRAIN_MM
            e, grains = (s - along) * rise, self._grain(s)
        weights = np.exp(-0.5 * (2.0 * e / reach) ** 2)
        return e[:, None] * smear[None, :], weights / weights.sum(), grains

    def _grain(self, along_mm: np.ndarray) -> np.ndarray:
        """The draws (K, 3) of the grains at positions along the wires (mm)."""
        return self._grains[np.floor(along_mm / WIRE_GRAIN_MM).astype(np.int64) % GRAIN_TABLE]

    def _add_dot(
        self, a: np.ndarray, u: float, v: float, amp: float, psf: Psf, rng: np.random.Generator,
        smear_px: np.ndarray | None = None, grain_at: tuple[float, float] | None = None,
    ) -> None:
        """Add one dot, smeared over the slice thickness along ``smear_px`` from the wire's grains
        at ``grain_at`` (see :meth:`_slice_samples`); with ``dot_texture``, modulated by a random
        patch of speckle."""
        offsets, weights, grains = self._slice_samples(self._start + v * self.sy, smear_px, grain_at)
        radius, rough = self.imaging.wire_diameter_mm / 2, self.imaging.wire_roughness
        if grains is None and (radius or rough):
            grains = rng.random((len(weights), 3))
        if radius and grains is not None:  # each echo from its grain's point of the rough wire's cross-section
            rho, theta = radius * np.sqrt(grains[:, 1]), 2 * np.pi * grains[:, 2]
            offsets = offsets + np.column_stack([rho * np.cos(theta) / self.sx, rho * np.sin(theta) / self.sy])
        lo, hi = offsets.min(axis=0), offsets.max(axis=0)
        (cu, cv), (ru, rv) = (u, v) + (lo + hi) / 2, (hi - lo) / 2
        half_x, above, below = psf.half_x, psf.above_z, psf.below_z
        if psf.beam_rad:  # a turned beam's patch reaches as far every way
            half_x = above = below = max(half_x, above, below)
        win = self._window(cu, cv, half_x + ru * self.sx, above + rv * self.sy, below + rv * self.sy)
        if win is None:
            return
        r0, r1, c0, c1 = win
        rows, cols = np.arange(r0, r1) - v, np.arange(c0, c1) - u
        if rough and len(weights) > 1 and grains is not None:  # echoes of a rough wire add with their grains' phases
            n_eff = 1.0 / float(np.sum(weights**2))
            phases = np.exp(2j * np.pi * grains[:, 0])
            weights = weights * ((1.0 - rough) + rough * np.sqrt(n_eff) * phases)
        patch = (amp * np.abs(self._echo_sum(rows, cols, offsets, weights, psf))).astype(np.float32)
        if self.noise.dot_texture:
            tex = self._textures[rng.integers(len(self._textures))]
            y, x = rng.integers(0, TEXTURE_PAD + 1, 2)
            patch *= 1.0 + self.noise.dot_texture * (tex[y : y + r1 - r0, x : x + c1 - c0] - 1.0)
        a[r0:r1, c0:c1] += patch

    def _echo_sum(self, rows: np.ndarray, cols: np.ndarray, offsets: np.ndarray, weights: np.ndarray,
                  psf: Psf) -> np.ndarray:
        """(R, C) the echoes from ``offsets`` (K, 2) px summed with ``weights`` (K,) on the patch's
        grid (row and column offsets from the wire, px), :data:`ECHO_BATCH` samples at a time: all K
        at once would take K times a patch's memory, and at a fine spacing a patch is the frame."""
        step = max(1, ECHO_BATCH // (len(rows) * len(cols)))
        total: np.ndarray | float = 0.0
        for k in range(0, len(weights), step):
            batch = slice(k, k + step)
            echoes = self._dot_patch(rows[None, :] - offsets[batch, 1:], cols[None, :] - offsets[batch, :1], psf)
            total = total + np.tensordot(weights[batch], echoes, axes=1)
        return np.asarray(total)

    def _add_wire_echo(
        self, a: np.ndarray, u: float, v: float, amp: float, direction: np.ndarray, rng: np.random.Generator,
        along_mm: float = np.nan,
    ) -> None:
        """One wire's echo at pixel (u, v) for its unit direction in the image frame: weaker and
        longer the more the wire tilts toward the beam, smeared across the slice, ringing below;
        from the wire's own grains where ``along_mm`` says where the crossing sits along the
        wires (NaN: grains drawn anew)."""
        im = self.imaging
        beam, depth = (float(x) for x in self.probe.beam_at(u, v))
        psf = replace(self.psf(depth), beam_rad=beam)
        axial = float(_beam_axes(direction[0], direction[1], beam)[1])
        tilt = axial**2 / 0.25  # sin^2 of the tilt toward the beam, re 30 degrees
        if im.incidence_widening and tilt:
            k = 1.0 + im.incidence_widening * tilt
            psf = replace(psf, sigma_z=psf.sigma_z * k, above_z=psf.above_z * k, below_z=psf.below_z * k)
        amp *= 10 ** (-im.incidence_loss_db * tilt / 20)
        ez = float(direction[2])
        smear = None
        if abs(ez) > 1e-6:
            smear = np.clip(np.asarray(direction[:2]) / ez, -MAX_SMEAR, MAX_SMEAR) / (self.sx, self.sy)
        grain_at = (float(along_mm), ez) if np.isfinite(along_mm) else None
        self._add_dot(a, u, v, amp, psf, rng, smear, grain_at)
        if np.isfinite(im.ringdown_db):
            self._add_comet(a, u, v, amp * 10 ** (im.ringdown_db / 20), psf.sigma_x, im.ringdown_mm, beam)

    def _add_blob(
        self, a: np.ndarray, u: float, v: float, amp: float, sigma_x: float, sigma_z: float
    ) -> None:
        """Add a plain separable Gaussian blob (sigmas in mm)."""
        win = self._window(u, v, 3 * sigma_x, 3 * sigma_z, 3 * sigma_z)
        if win is None:
            return
        r0, r1, c0, c1 = win
        x, z = (np.arange(c0, c1) - u) * self.sx, (np.arange(r0, r1) - v) * self.sy
        blob = np.outer(np.exp(-0.5 * (z / sigma_z) ** 2), np.exp(-0.5 * (x / sigma_x) ** 2))
        a[r0:r1, c0:c1] += (amp * blob).astype(np.float32)

    def _add_comet(
        self, a: np.ndarray, u: float, v: float, amp: float, sigma_x: float, length_mm: float, beam_rad: float = 0.0
    ) -> None:
        """Add a comet tail below (u, v) along the beam (``beam_rad``): a ring-down of echoes every
        0.35 mm over ``length_mm``."""
        reach = max(length_mm, 1.5 * sigma_x) if beam_rad else 1.5 * sigma_x
        win = self._window(u, v, reach, length_mm if beam_rad else 0.0, length_mm)
        if win is None:
            return
        r0, r1, c0, c1 = win
        x, z = _beam_axes(((np.arange(c0, c1) - u) * self.sx)[None, :], ((np.arange(r0, r1) - v) * self.sy)[:, None],
                          beam_rad)
        z = np.maximum(z, 0.0)
        ring = (0.55 + 0.45 * np.cos(2 * np.pi * z / 0.35)) * np.exp(-3.0 * z / length_mm)
        streak = amp * ring * np.exp(-0.5 * (x / (0.6 * sigma_x)) ** 2)
        a[r0:r1, c0:c1] += streak.astype(np.float32)

    def _add_line(self, a: np.ndarray, rows: np.ndarray, amp: np.ndarray) -> None:
        """Add a specular line: per column a sub-pixel row (NaN: none) and a linear amplitude."""
        h, _ = a.shape
        cols = np.nonzero(np.isfinite(rows) & (amp > 0))[0]
        up = int(np.ceil(4 * self._sigma_z / self.sy)) + 1
        down = int(np.ceil(5 * self.imaging.tail_length_mm / self.sy)) + 1
        r = rows[cols]
        rr = np.floor(r).astype(int) + np.arange(-up, down + 1)[:, None]  # (k, n), unique pixels
        val = amp[cols] * axial_profile((rr - r) * self.sy, self._sigma_z, self.imaging)
        inside = (rr >= 0) & (rr < h)
        a[rr[inside], np.broadcast_to(cols, rr.shape)[inside]] += val[inside].astype(np.float32)

    def _shade_below(self, a: np.ndarray, rows: np.ndarray, shadow_db: float) -> None:
        """Multiply ``a`` by a gain fading from 1 at ``rows`` (per column) to ``shadow_db`` 1 mm
        below them."""
        h, _ = a.shape
        if not np.isfinite(rows).any():
            return
        r0 = int(np.clip(np.floor(np.nanmin(rows)), 0, h))
        below_mm = (np.arange(r0, h)[:, None] - np.nan_to_num(rows, nan=np.inf)[None, :]) * self.sy
        fade = (1.0 - 10 ** (shadow_db / 20)) * np.clip(below_mm, 0.0, 1.0)
        a[r0:] *= (1.0 - fade).astype(np.float32)

    def _surface_amplitude(self, rows: np.ndarray) -> np.ndarray:
        """Specular echo amplitude per column: cos^4 of the incidence angle, blurred laterally."""
        slope = np.gradient(np.nan_to_num(rows) * self.sy) / self.sx
        amp = 10 ** (self.imaging.surface_db / 20) / (1.0 + slope**2) ** 2
        amp = np.where(np.isfinite(rows), amp, 0.0)
        return _blur_1d(amp, 0.5 * self.psf(25.0).sigma_x / self.sx, cv2.BORDER_CONSTANT)

    def _add_tank(self, a: np.ndarray, rows: np.ndarray) -> None:
        """Tank bottom: shadow, bright line, short ringing below it, a copy at twice the depth."""
        im = self.imaging
        self._shade_below(a, rows + 3 * self._sigma_z / self.sy, im.tank_shadow_db)
        level = 10 ** (im.tank_db / 20) * self._tank_gain
        self._add_line(a, rows, level)
        for k, db in enumerate(im.tank_ringing_db, start=1):
            self._add_line(a, rows + k * im.tank_ringing_mm / self.sy, level * 10 ** (db / 20))
        self._add_line(a, 2.0 * rows, level * 10 ** (im.tank_double_db / 20))

    def _compress(self, a: np.ndarray) -> np.ndarray:
        """Log compression over the dynamic range with saturation, then the gray map: uint8."""
        logs = cv2.log(cv2.max(a, self._floor))  # type: ignore[call-overload]  # the cv2 stub lacks max(array, scalar)
        idx = cv2.addWeighted(logs, self._log_scale, logs, 0.0, 255.0, dtype=cv2.CV_8U)
        return cv2.LUT(idx, self._gray_lut)

    # --- noise -----------------------------------------------------------------------------------

    def _speckle(self, rng: np.random.Generator) -> np.ndarray:
        """Background speckle amplitude: a random crop of a random texture, randomly flipped."""
        h, w = self.shape
        tex = self._textures[rng.integers(len(self._textures))]
        dy, dx = rng.integers(0, TEXTURE_PAD + 1, 2)
        fy, fx = np.where(rng.integers(0, 2, 2) == 1, -1, 1)
        level = np.float32(10 ** (self.noise.speckle_db / 20))
        return tex[dy : dy + h, dx : dx + w][::fy, ::fx] * level

    def _add_particles(self, a: np.ndarray, rng: np.random.Generator) -> None:
        """Small suspended particles: tiny dim Gaussian dots."""
        nm = self.noise
        n = rng.poisson(nm.particle_rate) if nm.particle_rate else 0
        h, w = self.shape
        us, vs, dbs = rng.uniform(0, w, n), rng.uniform(0, h, n), rng.uniform(*nm.particle_db, n)
        for u, v, db in zip(us, vs, dbs):
            self._add_blob(a, u, v, 10 ** (db / 20), 0.12, 0.08)

    def _add_bubbles(self, a: np.ndarray, rng: np.random.Generator) -> None:
        """Bubbles: bright blobs the size of wire dots, some ringing down into a comet tail."""
        nm = self.noise
        n = rng.poisson(nm.bubble_rate) if nm.bubble_rate else 0
        h, w = self.shape
        for _ in range(n):
            u, v = rng.uniform(0, w), rng.uniform(0, h)
            amp = 10 ** (rng.uniform(*nm.bubble_db) / 20)
            beam, depth = (float(x) for x in self.probe.beam_at(u, v))
            psf = self.psf(depth)
            psf = replace(psf, sigma_x=psf.sigma_x * rng.uniform(0.6, 1.2), beam_rad=beam)
            self._add_dot(a, u, v, amp, psf, rng)
            if rng.random() < nm.comet_fraction:
                self._add_comet(a, u, v, 0.3 * amp, psf.sigma_x, rng.uniform(2.0, 6.0), beam)

    # --- frames ----------------------------------------------------------------------------------

    def render(
        self,
        dots_px: np.ndarray,
        weights: np.ndarray | None = None,
        surface_rows: np.ndarray | None = None,
        tank_bottom_row: float | np.ndarray | None = None,
        rng: np.random.Generator | None = None,
        directions: np.ndarray | None = None,
        along_mm: np.ndarray | None = None,
    ) -> np.ndarray:
        """One (height_px, width_px) uint8 frame.

        ``dots_px``: (N, 2) wire centres (u = column, v = row) in float pixels at the true spacing;
        rows with NaN are skipped. ``weights``: (N,) linear amplitude factors (default 1).
        ``surface_rows``: (width_px,) sub-pixel row of a specular object surface per column, NaN
        where there is none. ``tank_bottom_row``: the tank bottom's row, a scalar or one per
        column. ``rng`` defaults to the renderer's own generator, seeded at construction.
        ``directions``: (N, 3) unit wire directions in the image frame (x lateral, y depth, z
        elevation), for the slice thickness and the incidence angle; None: wires along the normal.
        ``along_mm``: (N,) where each crossing sits along the phantom's wires laid end to end
        (mm): a rough wire's grains stay where they are on it, so its echo changes only as the
        crossing moves; None: a rough wire's grains are drawn anew in every frame.
        """
        rng = self._rng if rng is None else rng
        nm, im = self.noise, self.imaging
        _, w = self.shape
        dots = np.asarray(dots_px, dtype=float).reshape(-1, 2)
        gains = np.ones(len(dots)) if weights is None else np.asarray(weights, dtype=float)
        amps = 10 ** (im.dot_db / 20) * np.broadcast_to(gains, len(dots))
        if nm.dot_jitter_db:
            amps = amps * 10 ** (rng.uniform(-nm.dot_jitter_db, nm.dot_jitter_db, len(dots)) / 20)
        if nm.dot_dropout:
            faded = rng.random(len(dots)) < nm.dot_dropout
            amps = amps * np.where(faded, 10 ** (rng.uniform(*nm.dropout_db, len(dots)) / 20), 1.0)
        keep = np.isfinite(dots).all(axis=1)
        dirs = np.tile([0.0, 0.0, 1.0], (len(dots), 1)) if directions is None else np.asarray(directions, float)

        a = self._speckle(rng) if np.isfinite(nm.speckle_db) else np.zeros(self.shape, np.float32)
        if np.isfinite(nm.reverb_db):
            level = 10 ** ((nm.reverb_db + rng.uniform(-1.5, 1.5)) / 20)
            a[: len(self._reverb)] += np.float32(level) * self._reverb
        along = np.full(len(dots), np.nan) if along_mm is None else np.asarray(along_mm, float)
        for (u, v), amp, direction, at in zip(dots[keep], amps[keep], dirs[keep], along[keep]):
            self._add_wire_echo(a, u, v, amp, direction, rng, at)
        self._add_particles(a, rng)
        self._add_bubbles(a, rng)

        if surface_rows is not None:
            rows = np.asarray(surface_rows, dtype=float).reshape(w)
            self._shade_below(a, rows + 3 * self._sigma_z / self.sy, im.surface_shadow_db)
            self._add_line(a, rows, self._surface_amplitude(rows))
        if tank_bottom_row is not None:
            rows = np.broadcast_to(np.asarray(tank_bottom_row, dtype=float), (w,)) + self._tank_rows
            self._add_tank(a, rows)

        gain_db = self._base_gain_db
        if nm.tgc_jitter_db:
            knots = np.linspace(0.0, self._depth[-1], 9)
            jitter = rng.uniform(-nm.tgc_jitter_db, nm.tgc_jitter_db, knots.size)
            gain_db = gain_db + np.interp(self._depth, knots, jitter)
        a *= (10 ** (gain_db / 20)).astype(np.float32)[:, None]
        image = self._compress(a)
        if self._outside_fan is not None:
            image[self._outside_fan] = 0
        return image


def _beam_axes(x: np.ndarray, z: np.ndarray, beam_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Image offsets (x lateral, z down; any units) in a beam's own axes (lateral, axial), the beam
    turned ``beam_rad`` from the image's downward axis toward +x."""
    c, s = np.cos(beam_rad), np.sin(beam_rad)
    return x * c - z * s, x * s + z * c


@lru_cache(maxsize=8)
def renderer(probe: Probe, noise: str = "realistic", seed: int = 0) -> BModeRenderer:
    """A shared renderer per (probe, noise level, seed); construction takes about 0.1 s."""
    return BModeRenderer(probe, noise, seed)


def render_bmode(
    probe: Probe,
    dots_px: np.ndarray,
    rng: np.random.Generator,
    noise: str = "realistic",
    weights: np.ndarray | None = None,
    surface_rows: np.ndarray | None = None,
    tank_bottom_row: float | np.ndarray | None = None,
) -> np.ndarray:
    """One uint8 B-mode frame from a shared renderer; see :meth:`BModeRenderer.render`."""
    return renderer(probe, noise).render(dots_px, weights, surface_rows, tank_bottom_row, rng)
