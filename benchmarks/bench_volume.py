"""Volume compounding (core.volume.compound): agreement with PLUS, insertion speed and memory.

1. PLUS's own test: SpinePhantomFreehand.igs.mha reconstructed with the NN_MEAN and LN_MAXI
   device-set files, compared with PLUS's reference volumes (grid, voxel-wise Pearson correlation
   over voxels nonzero in both, fraction nonzero in only one). Target: correlation >= 0.99.
2. Insertion rate of synthetic 820x616 frames into 0.5 mm voxels, per interpolation and
   compounding mode. Target: >= 100 frames/s.
3. A 2,000-frame synthetic sweep fed by a generator, one frame at a time: peak RSS; and
   ``probecal reconstruct`` of a 600-frame sweep without and with ``--cad`` (within 2x).
4. The simulated test object (5 passes x 120 frames) reconstructed with the true calibration and
   with the one `probecal calibrate` estimates from a calibration sweep of the same set-up,
   compared with its CAD model. Targets: mean <= 0.3 / 95th percentile <= 1.0 mm (true) and
   <= 0.5 / 1.5 mm (estimated).

Run: .venv/bin/python benchmarks/bench_volume.py [--write-docs]
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numba
import numpy as np
from evidence import WRITE_DOCS, command_line, markdown_table, write_table

from probecal.core.io.deviceset import read_device_set
from probecal.core.io.plusdata import plus_data_dir
from probecal.core.io.sequence import read_sequence
from probecal.core.volume.cad import session_cad_target
from probecal.core.volume.compound import Compounder, fill_holes, nearest_voxel, reconstruct_sequence
from probecal.core.volume.grid import Volume, VolumeSettings, output_grid, settings_from_device_set
from probecal.core.volume.reconstruct import reconstruct_plus
from probecal.core.volume.volumefile import read_volume

PLUS = plus_data_dir()
SEQUENCE = PLUS / "TestImages" / "SpinePhantomFreehand.igs.mha"
CONFIGS = PLUS / "ConfigFiles" / "Testing"
CASES = {"NN_MEAN": "NNMEAN", "LN_MAXI": "LNMAXI"}
WIDTH, HEIGHT, PIXEL_MM = 820, 616, 0.08
TABLE = ("compounding", "grid (dimensions, origin, spacing)", "voxels' correlation with PLUS's", "voxels identical")


def compare_with_plus() -> list[list[str]]:
    """Print the comparison of each case with PLUS's reference volume; the rows of :data:`TABLE`."""
    rows = []
    for config_name, ref_name in CASES.items():
        config = CONFIGS / f"PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_{config_name}.xml"
        start = time.perf_counter()
        ours = reconstruct_plus(SEQUENCE, config)
        seconds = time.perf_counter() - start
        ref = read_volume(PLUS / "TestImages" / f"vtkVolumeReconstructorTest{ref_name}volumeRef.mha")
        a, b = ours.voxels.astype(float), ref.voxels.astype(float)
        both = (a > 0) & (b > 0)
        only_one = (a > 0) ^ (b > 0)
        faint = only_one & (np.maximum(a, b) <= 3)
        print(f"PLUS {config_name}: reconstructed in {seconds:.2f} s (incl. reading the sequence)")
        print(f"  dims (x y z) ours {ours.voxels.shape[::-1]}, PLUS {ref.voxels.shape[::-1]}")
        print(f"  origin ours {np.round(ours.origin_mm, 4).tolist()}, PLUS {list(ref.origin_mm)}")
        print(f"  spacing ours {list(ours.spacing_mm)}, PLUS {list(ref.spacing_mm)}")
        r = np.corrcoef(a[both], b[both])[0, 1]
        print(f"  Pearson r over {both.sum()} voxels nonzero in both: {r:.4f}")
        print(f"  mean(ours - PLUS) there: {np.mean(a[both] - b[both]):+.2f} gray levels")
        print(
            f"  nonzero in one only: {only_one.mean():.2%} of voxels"
            f" ({faint.sum() / max(only_one.sum(), 1):.0%} of them at gray level <= 3);"
            f" equal voxels {np.mean(a == b):.1%}"
        )
        if config_name == "NN_MEAN":
            truncated_mean_explains_the_difference(config, b)
        rows.append([config_name, grid_agreement(ours, ref), f"r = {r:.4f}", f"{np.mean(a == b):.1%}"])
    return rows


def grid_agreement(ours: Volume, ref: Volume) -> str:
    """'identical', or which of the grid's dimensions, origin and spacing differ from PLUS's."""
    differ = [name for name, same in (
        ("dimensions", ours.voxels.shape == ref.voxels.shape),
        ("origin", np.allclose(ours.origin_mm, ref.origin_mm, atol=1e-4)),
        ("spacing", np.allclose(ours.spacing_mm, ref.spacing_mm)),
    ) if not same]
    return f"{', '.join(differ)} differ" if differ else "identical"


@numba.njit
def _running_mean(pixels, x0, y0, to_index, shape, voxels, counts):
    """PLUS's NEAREST_NEIGHBOR MEAN as its 8-bit output keeps it: a running mean, truncated to a
    whole gray level after every pixel."""
    for row in range(pixels.shape[0]):
        for column in range(pixels.shape[1]):
            k = nearest_voxel(to_index, x0 + column, y0 + row, shape)
            if k >= 0:
                voxels[k] = np.floor((voxels[k] * counts[k] + pixels[row, column]) / (counts[k] + 1))
                counts[k] += 1


def truncated_mean_explains_the_difference(config, reference: np.ndarray) -> None:
    """The NN_MEAN volume with PLUS's truncated running mean instead of probecal's exact one."""
    device_set = read_device_set(config)
    settings = settings_from_device_set(device_set)
    seq = read_sequence(SEQUENCE)
    tool_to_reference, valid = seq.transform("Probe", "Reference")
    image_to_probe = device_set.transform("Image", "Probe")
    poses = [m @ image_to_probe if ok else None for m, ok in zip(tool_to_reference, valid)]
    height, width = seq.frames.shape[1:]
    grid = output_grid(settings, (width, height), poses)
    x0, y0, x1, y1 = settings.clip_rectangle(width, height)
    voxels, counts = np.zeros(int(np.prod(grid.shape))), np.zeros(int(np.prod(grid.shape)), np.int64)
    for frame, pose in zip(seq.frames, poses):
        if pose is not None:
            _running_mean(frame[y0 : y1 + 1, x0 : x1 + 1], x0, y0, grid.volume_to_index @ pose, grid.shape, voxels,
                          counts)
    values = fill_holes(voxels.reshape(grid.shape).astype(np.uint8), (counts > 0).reshape(grid.shape),
                        settings.stick_length, settings.sticks_used).astype(float)
    both = (values > 0) & (reference > 0)
    print(f"  with PLUS's running mean truncated after every pixel instead of the exact mean: "
          f"{np.mean(values == reference):.1%} of voxels equal to PLUS's, mean difference "
          f"{np.mean(values[both] - reference[both]):+.2f} gray levels")


def sweep_pose(i: int, step_mm: float = 0.05) -> np.ndarray:
    """image_to_volume of frame i of a synthetic sweep: the image plane (x right, y depth) moves
    along the elevation (z) axis with a slow wobble, pixel spacing PIXEL_MM."""
    angle = np.radians(3.0 * np.sin(i / 40.0))
    rotation = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    out = np.eye(4)
    out[:3, :3] = rotation @ np.diag([PIXEL_MM, PIXEL_MM, 1.0])
    out[:3, 3] = [0.0, 0.0, i * step_mm]
    return out


def synthetic_frame(i: int, base: np.ndarray) -> np.ndarray:
    """A speckle-like frame that changes from frame to frame (cheap to make)."""
    return np.roll(base, i, axis=1)


def insertion_rate(settings: VolumeSettings, frames: int = 150) -> tuple[float, tuple[int, int, int]]:
    base = np.random.default_rng(0).integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
    poses = [sweep_pose(i) for i in range(frames)]
    grid = output_grid(settings, (WIDTH, HEIGHT), poses)
    compounder = Compounder(settings, grid)
    images = [synthetic_frame(i, base) for i in range(frames)]
    compounder.insert(images[0], poses[0])
    start = time.perf_counter()
    for image, pose in zip(images[1:], poses[1:]):
        compounder.insert(image, pose)
    return (frames - 1) / (time.perf_counter() - start), grid.shape


def speed() -> None:
    for interpolation in ("NEAREST_NEIGHBOR", "LINEAR"):
        for compounding in ("MEAN", "MAXIMUM", "LATEST"):
            rate, shape = insertion_rate(VolumeSettings(interpolation=interpolation, compounding=compounding))
            print(
                f"insert {WIDTH}x{HEIGHT} frames into 0.5 mm voxels ({shape[2]}x{shape[1]}x{shape[0]}),"
                f" {interpolation:>16} {compounding:>7}: {rate:6.1f} frames/s"
            )


def memory(frames: int = 2000) -> None:
    base = np.random.default_rng(1).integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    def generate():
        for i in range(frames):
            yield synthetic_frame(i, base)

    settings = VolumeSettings(fill_holes=True)
    start = time.perf_counter()
    volume = reconstruct_sequence(generate(), (sweep_pose(i) for i in range(frames)), settings)
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    nz, ny, nx = volume.voxels.shape
    print(
        f"{frames}-frame sweep from a generator (NN MEAN + hole filling): {seconds:.1f} s,"
        f" volume {nx}x{ny}x{nz} ({volume.voxels.nbytes / 2**20:.0f} MiB),"
        f" frames would total {frames * WIDTH * HEIGHT / 2**20:.0f} MiB"
    )
    print(f"  peak RSS {peak:.0f} MiB (was {before:.0f} MiB before the sweep)")


def surface_accuracy(seeds: int = 3) -> None:
    import tempfile

    from probecal.core.acquisition.simulate import simulate_calibration, simulate_volume
    from probecal.core.calibration.result import load_calibration
    from probecal.core.calibration.segment import segment_session
    from probecal.core.calibration.solve import calibrate_session
    from probecal.core.volume.reconstruct import reconstruct_session

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rows = {"true": [], "estimated": []}
        for seed in range(seeds):
            volume = simulate_volume(tmp / f"v{seed}", seed=seed)
            calibration_sweep = simulate_calibration(tmp / f"c{seed}", n_poses=60, seed=seed)
            estimated = calibrate_session(calibration_sweep, segment_session(calibration_sweep),
                                          with_validation=False).calibration
            cad = session_cad_target(volume)
            for name, calibration in (("true", load_calibration(volume.path / "truth.json")), ("estimated", estimated)):
                start = time.perf_counter()
                report = reconstruct_session(volume, calibration, tmp / f"r{seed}{name}", cad=cad).report
                rows[name].append((report["surface_mean_mm"], report["surface_p95_mm"], report["cad_to_points_mean_mm"],
                                   report["cad_to_points_p95_mm"], len(volume) / (time.perf_counter() - start)))
        for name, target in (("true", "0.3 / 1.0"), ("estimated", "0.5 / 1.5")):
            a = np.array(rows[name])
            print(f"simulated object, {name} calibration ({seeds} seeds, {len(volume)} frames each): points->CAD mean "
                  f"{a[:, 0].mean():.3f} mm (worst {a[:, 0].max():.3f}), p95 {a[:, 1].mean():.3f} mm (worst "
                  f"{a[:, 1].max():.3f}) [target {target}]; CAD->points mean {a[:, 2].mean():.3f}, p95 "
                  f"{a[:, 3].mean():.3f} mm; whole reconstruction {a[:, 4].mean():.0f} frames/s")


def cad_memory() -> None:
    """Peak memory of ``probecal reconstruct`` on a 600-frame simulated sweep, without and with
    --cad (issue 18: within 2x)."""
    import subprocess
    import tempfile

    probecal = Path(sys.executable).parent / "probecal"
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        subprocess.run([str(probecal), "simulate", "volume", str(tmp / "vol")], check=True, capture_output=True)
        peaks = []
        for name, extra in (("alone", []), ("with --cad", ["--cad", str(tmp / "vol" / "test_object.stl")])):
            subprocess.run([str(probecal), "reconstruct", str(tmp / "vol"), "--calibration",
                            str(tmp / "vol" / "truth.json"), "--out", str(tmp / name), *extra],
                           check=True, capture_output=True)
            peaks.append(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)
        print(f"probecal reconstruct, 600 frames: peak RSS {peaks[0]:.0f} MiB alone, {peaks[1]:.0f} MiB with --cad "
              f"({peaks[1] / peaks[0]:.2f}x, target <= 2x)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(WRITE_DOCS, action="store_true", help="write the table into docs/evidence (evidence.py)")
    args = parser.parse_args()
    if args.write_docs and not PLUS.is_dir():
        parser.error(f"{WRITE_DOCS} needs PLUS's data, not found at {PLUS}")
    cad_memory()
    memory()
    surface_accuracy()
    rows = []
    if PLUS.is_dir():
        rows = compare_with_plus()
    else:
        print(f"PLUS data not found at {PLUS}; skipping the comparison")
    speed()
    if args.write_docs:
        print(f"written: {write_table(command_line(), markdown_table(TABLE, rows))}")


if __name__ == "__main__":
    main()
