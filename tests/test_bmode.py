"""B-mode synthesis (core/twin/bmode.py) against design §4: dot shape, centring, noise levels, speed."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from probecal.core.geometry.probe import LinearProbe
from probecal.core.twin.bmode import BModeRenderer, render_bmode
from probecal.core.twin.imaging import NOISE_LEVELS, ImagingModel, dot_amplitude

PROBE = LinearProbe()
SX, SY = PROBE.true_spacing_mm


def dot_px(x_mm: float, depth_mm: float) -> tuple[float, float]:
    return x_mm / SX, depth_mm / SY


def twelve_dots() -> np.ndarray:
    """Four N layers at 10-40 mm, outer wires 30 mm apart, sub-pixel positions."""
    return np.array(
        [
            dot_px(x, depth)
            for depth, ratio in zip((10.3, 20.6, 30.1, 39.8), (0.3, 0.55, 0.75, 0.4))
            for x in (4.27, 4.27 + 30.0 * ratio, 34.27)
        ]
    )


def blobs(img: np.ndarray, threshold: float) -> list[tuple[float, float]]:
    """Intensity-weighted centroids (u, v) of the 8-connected components >= threshold."""
    mask = (img >= threshold).astype(np.uint8)
    n, labels, _, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    out = []
    for k in range(1, n):
        ys, xs = np.nonzero(labels == k)
        w = img[ys, xs].astype(float)
        out.append(((xs * w).sum() / w.sum(), (ys * w).sum() / w.sum()))
    return out


def fwhm_px(profile: np.ndarray, centre: int) -> float:
    """Full width at half the profile's maximum around ``centre``, edges interpolated."""
    p = profile.astype(float)
    half = p.max() / 2
    left, right = centre, centre
    while left > 0 and p[left - 1] >= half:
        left -= 1
    while right < p.size - 1 and p[right + 1] >= half:
        right += 1
    lo = left - 1 + (half - p[left - 1]) / (p[left] - p[left - 1])
    hi = right + (p[right] - half) / (p[right] - p[right + 1])
    return hi - lo


@pytest.fixture(scope="module")
def renderers() -> dict[str, BModeRenderer]:
    return {level: BModeRenderer(PROBE, level, seed=7) for level in NOISE_LEVELS}


def test_shape_and_dtype(renderers):
    for r in renderers.values():
        img = r.render(twelve_dots(), tank_bottom_row=46.0 / SY)
        assert img.shape == (PROBE.height_px, PROBE.width_px) and img.dtype == np.uint8
    big = LinearProbe(width_px=820, height_px=616)
    img = BModeRenderer(big, "harsh").render(np.array([[400.0, 300.0]]))
    assert img.shape == (616, 820) and img.dtype == np.uint8


@pytest.mark.parametrize("depth_mm", [10.0, 25.0, 40.0])
def test_echo_peaks_on_the_wire_without_noise(renderers, depth_mm):
    """The main lobe peaks on the wire, the tail trails below it; the half-maximum centroid
    stays within 0.05 mm of the wire."""
    psf = renderers["none"].psf(depth_mm)
    x, z = np.linspace(-1, 1, 201), np.linspace(-1, 1, 201)
    amplitude = dot_amplitude(x, z, psf.sigma_x, psf.sigma_z, renderers["none"].imaging)
    assert np.unravel_index(amplitude.argmax(), amplitude.shape) == (100, 100)
    assert amplitude[110:, 100].sum() > amplitude[:91, 100].sum()  # more echo below than above
    errors = []
    for x_mm, dv in [(8.0, 0.0), (19.13, 0.37), (30.61, 0.71)]:
        u, v = dot_px(x_mm, depth_mm)
        v += dv
        img = renderers["none"].render(np.array([[u, v]]))
        (cu, cv), = blobs(img, 0.5 * img.max())
        errors.append(np.hypot((cu - u) * SX, (cv - v) * SY))
    assert max(errors) < 0.05, errors


def test_dots_saturated(renderers):
    dots = twelve_dots()
    for level in ("none", "realistic"):
        for _ in range(5):
            img = renderers[level].render(dots)
            centres = img[np.round(dots[:, 1]).astype(int), np.round(dots[:, 0]).astype(int)]
            assert np.all(centres == 255), (level, centres)


def test_widths_follow_spec(renderers):
    lateral, axial = {}, {}
    for depth_mm in (15.0, 25.0, 35.0):
        u, v = dot_px(19.2, depth_mm)
        img = renderers["none"].render(np.array([[u, v]]))
        (cu, cv), = blobs(img, 0.5 * img.max())
        lateral[depth_mm] = fwhm_px(img[round(cv)], round(cu)) * SX
        axial[depth_mm] = fwhm_px(img[:, round(cu)], round(cv)) * SY
    assert lateral[15.0] < lateral[25.0] < lateral[35.0]
    assert 0.7 * 0.7 <= lateral[15.0] <= 0.7 * 1.3, lateral
    assert 2.0 * 0.7 <= lateral[35.0] <= 2.0 * 1.3, lateral
    assert all(0.5 <= a <= 0.9 for a in axial.values()), axial


def test_smile_and_tail(renderers):
    """The echo's ends bend toward the probe; a fainter tail extends below the dot."""
    u, v = dot_px(19.2, 35.0)
    img = renderers["none"].render(np.array([[u, v]])).astype(float)
    c, r = round(u), round(v)
    rows = np.arange(r - 20, r + 20)[:, None]
    patch = img[r - 20 : r + 20]
    mean_row = (patch * rows).sum(axis=0) / np.maximum(patch.sum(axis=0), 1e-9)
    ends = [c - round(1.6 / SX), c + round(1.6 / SX)]
    assert np.all((mean_row[c] - mean_row[ends]) * SY > 0.1)
    below = img[r + round(0.6 / SY), c]
    assert 0 < below < 200


def test_background_nearly_black(renderers):
    img = renderers["realistic"].render(twelve_dots(), tank_bottom_row=46.0 / SY)
    assert np.median(img) < 10
    assert np.count_nonzero(renderers["none"].render(np.empty((0, 2)))) == 0


def test_harsh_has_more_false_blobs(renderers):
    dots = twelve_dots()

    def false_blobs(level: str) -> int:
        count = 0
        for _ in range(10):
            img = renderers[level].render(dots)
            for cu, cv in blobs(img, 128):
                d = np.hypot((dots[:, 0] - cu) * SX, (dots[:, 1] - cv) * SY).min()
                count += d > 1.5
        return count

    assert false_blobs("harsh") > false_blobs("realistic") + 10


def test_deterministic_with_seed():
    dots = twelve_dots()
    a = [BModeRenderer(PROBE, "harsh", seed=3).render(dots) for _ in range(2)]
    assert np.array_equal(a[0], a[1])
    r = BModeRenderer(PROBE, "harsh", seed=3)
    twins = [r.render(dots, rng=np.random.default_rng(1)) for _ in range(2)]
    assert np.array_equal(twins[0], twins[1])
    assert not np.array_equal(a[0], BModeRenderer(PROBE, "harsh", seed=4).render(dots))
    none = [render_bmode(PROBE, dots, np.random.default_rng(s), noise="none") for s in (1, 2)]
    assert np.array_equal(none[0], none[1])


def test_surface_line_and_shadow():
    r = BModeRenderer(PROBE, "harsh", seed=1)
    cols = np.arange(PROBE.width_px)
    surface = np.full(PROBE.width_px, np.nan)
    inside = (cols >= 100) & (cols < 300)
    surface[inside] = (20.0 + 2.0 * np.sin(cols[inside] / 30.0)) / SY
    img = r.render(np.empty((0, 2)), surface_rows=surface).astype(float)
    for c in range(120, 281, 20):
        assert abs(np.argmax(img[:, c]) - surface[c]) <= 1.5
        assert img[round(surface[c]) - 1 : round(surface[c]) + 2, c].max() >= 200
    band = slice(round(25.0 / SY), round(35.0 / SY))
    shadow, open_water = img[band, 120:280].mean(), img[band, 320:].mean()
    assert shadow < 0.3 * open_water


def test_tank_bottom_and_its_double():
    r = BModeRenderer(PROBE, "none")
    img = r.render(np.empty((0, 2)), tank_bottom_row=20.0 / SY)
    profile = img.max(axis=1).astype(int)
    bottom, double = round(20.0 / SY), round(40.0 / SY)
    assert profile[bottom - 2 : bottom + 3].max() > 100
    assert 0 < profile[double - 2 : double + 3].max() < profile[bottom - 2 : bottom + 3].max()
    assert profile[bottom + round(3.0 / SY) : double - 5].max() == 0


def test_imaging_model_widths():
    im = ImagingModel()
    assert im.lateral_fwhm_mm(15.0) == pytest.approx(0.7, abs=0.02)
    assert im.lateral_fwhm_mm(35.0) == pytest.approx(2.0, abs=0.02)


def test_bench_dots_stay_below_saturation_and_vary(renderers):
    """Real dots are not all white: at ``bench``, wires crossing the slice at 30 degrees peak
    below 255 (3x3 mean, as benchmarks/bench_realism.py measures) and differ in brightness."""
    dots = twelve_dots()
    directions = np.tile([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))], (len(dots), 1))
    peaks = []
    for _ in range(5):
        img = cv2.blur(renderers["bench"].render(dots, directions=directions).astype(float), (3, 3))
        peaks += [img[int(round(v)) - 3 : int(round(v)) + 4, int(round(u)) - 3 : int(round(u)) + 4].max()
                  for u, v in dots]
    peaks = np.array(peaks, float)
    assert np.median(peaks) < 250 and peaks.std() / peaks.mean() > 0.03


def _slice_renderer(**imaging) -> BModeRenderer:
    model = ImagingModel(elevation_fwhm_mm=2.5, elevation_focus_mm=20.0, elevation_divergence=0.08, **imaging)
    return BModeRenderer(PROBE, "none", seed=0, imaging=model)


def test_a_thick_slice_smears_an_oblique_wire_along_its_in_plane_direction():
    """A wire crossing the slice at 45 degrees in x echoes from every elevation inside it: its dot
    is wider laterally than that of a wire along the normal, and (smooth wire, no noise) still
    centred on the crossing."""
    renderer = _slice_renderer()
    u, v = 190.3, 250.6
    normal = renderer.render(np.array([[u, v]]), directions=np.array([[0.0, 0.0, 1.0]]))
    oblique = renderer.render(np.array([[u, v]]), directions=np.array([[np.sqrt(0.5), 0.0, np.sqrt(0.5)]]))
    row = int(round(v))
    assert fwhm_px(oblique[row], int(round(u))) > 1.5 * fwhm_px(normal[row], int(round(u)))
    (cu, cv), = blobs(oblique, 100)
    assert abs(cu - u) < 0.3 and abs(cv - v) < 1.0


def test_rough_wires_break_the_smear_into_speckle_that_moves_the_centroid():
    renderer = _slice_renderer(wire_roughness=1.0)
    u, v = 190.0, 250.0
    direction = np.array([[np.sqrt(0.5), 0.0, np.sqrt(0.5)]])
    centres = [blobs(renderer.render(np.array([[u, v]]), rng=np.random.default_rng(k), directions=direction), 60)
               for k in range(8)]
    lateral = [max(c, key=lambda p: -abs(p[0] - u))[0] for c in centres if c]
    assert np.std(lateral) > 0.2  # px; a smooth wire's centroid does not move at all


def test_a_rough_wires_grains_stay_on_it_so_its_echo_changes_only_as_the_crossing_moves():
    """Given where the crossing sits along the wire, every frame draws the same grains: the same
    crossing gives the same dot whatever the frame's noise draws; a crossing a grain or two
    further along moves the centroid a little, one a few millimetres on as much as fresh grains."""
    renderer = _slice_renderer(wire_roughness=1.0, wire_diameter_mm=0.3)
    u, v = 190.0, 250.0
    direction = np.array([[np.sqrt(0.5), 0.0, np.sqrt(0.5)]])

    def centre(along_mm: float, seed: int) -> float:
        image = renderer.render(np.array([[u, v]]), rng=np.random.default_rng(seed), directions=direction,
                                along_mm=np.array([along_mm]))
        return max(blobs(image, 60), key=lambda p: -abs(p[0] - u))[0]

    assert centre(40.0, 0) == centre(40.0, 1)
    near = [abs(centre(40.0 + k * 0.2, 0) - centre(40.0 + (k + 1) * 0.2, 0)) for k in range(12)]
    far = [abs(centre(40.0 + k * 3.0, 0) - centre(40.0 + (k + 1) * 3.0, 0)) for k in range(12)]
    assert np.mean(near) < 0.5 * np.mean(far)
    assert np.std([centre(40.0 + k * 3.0, 0) for k in range(12)]) > 0.2  # px, as fresh grains move it


def test_a_wire_tilted_toward_the_beam_echoes_weaker():
    renderer = BModeRenderer(PROBE, "none", seed=0, imaging=ImagingModel(dot_db=0.0, incidence_loss_db=6.0))
    u, v = 190.0, 250.0
    tilted = np.array([[0.0, np.sin(np.radians(30)), np.cos(np.radians(30))]])
    straight = renderer.render(np.array([[u, v]]), directions=np.array([[0.0, 0.0, 1.0]]))
    weak = renderer.render(np.array([[u, v]]), directions=tilted)
    assert weak.max() < straight.max() - 10


def test_a_rough_wire_of_some_diameter_echoes_unevenly_even_along_the_normal():
    """Its echoes come from random points of its cross-section, with random phases: the dot's
    centroid moves from frame to frame though the wire does not."""
    renderer = _slice_renderer(wire_roughness=1.0, wire_diameter_mm=0.3)
    u, v = 190.0, 250.0
    normal = np.array([[0.0, 0.0, 1.0]])
    centres = [blobs(renderer.render(np.array([[u, v]]), rng=np.random.default_rng(k), directions=normal), 60)[0]
               for k in range(8)]
    assert np.std([c[0] for c in centres]) > 0.05 and np.std([c[1] for c in centres]) > 0.05
    assert np.hypot(np.mean([c[0] for c in centres]) - u, np.mean([c[1] for c in centres]) - v) < 1.0
