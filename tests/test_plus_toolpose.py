"""Any PLUS recording imports (issue 14): the tool pose and the phantom pose are composed and
inverted, by frame names, from the transforms the recording and the device set hold."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from probecal.core.geometry.transforms import make_transform
from probecal.core.io.plusimport import import_plus
from probecal.core.io.sequence import TrackedSequence, read_sequence, write_sequence
from tests.support.cli import run_cli
from tests.support.paths import FCAL_VALIDATION, VLCUS_CONFIG
from tests.support.refusals import assert_one_line_error

N = 4


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 4, 4) random rigid transforms, translations within 200 mm."""
    return np.array([make_transform(Rotation.random(random_state=rng), rng.uniform(-200, 200, 3)) for _ in range(n)])


def stepper_recording(folder: Path, template_to_stepper_home: np.ndarray, name: str = "stepper.igs.mha",
                      probe_valid: np.ndarray | None = None, template_valid: np.ndarray | None = None) -> Path:
    """A stepper-style recording of the first N real fCal frames: their ProbeToTracker as
    ProbeToStepperHome, and the given TemplateToStepperHome (N, 4, 4)."""
    real = read_sequence(FCAL_VALIDATION)
    seq = TrackedSequence(
        frames=real.frames[:N],
        transforms={"ProbeToStepperHome": real.transforms["ProbeToTracker"][:N],
                    "TemplateToStepperHome": template_to_stepper_home},
        statuses={"ProbeToStepperHome": np.ones(N, bool) if probe_valid is None else probe_valid,
                  "TemplateToStepperHome": np.ones(N, bool) if template_valid is None else template_valid},
        timestamps=real.timestamps[:N],
    )
    write_sequence(folder / name, seq)
    return folder / name


def stepper_config(folder: Path, template_holder_to_template: np.ndarray) -> Path:
    """The real VLCUS device set (phantom, TemplateHolder->Phantom) with a TemplateHolder->Template
    transform added, so PhantomToTemplate is composed and inverted from two constants."""
    matrix = " ".join(repr(float(v)) for v in template_holder_to_template.ravel())
    text = VLCUS_CONFIG.read_text().replace(
        "</CoordinateDefinitions>", f'  <Transform From="TemplateHolder" To="Template" Matrix="{matrix}" />\n'
                                    "  </CoordinateDefinitions>")
    path = folder / "stepper.xml"
    path.write_text(text)
    return path


def test_stepper_recording_imports_as_probe_to_template(plus_data, tmp_path):
    rng = np.random.default_rng(14)
    recording = stepper_recording(tmp_path, random_poses(rng, N))
    seq = read_sequence(recording)
    session = import_plus(recording, None, tmp_path / "session", tool="Probe", reference="Template")
    expected = np.linalg.inv(seq.transforms["TemplateToStepperHome"]) @ seq.transforms["ProbeToStepperHome"]
    assert np.allclose(session.poses(), expected, atol=1e-9)
    assert all(r.pose_valid for r in session.records) and len(session) == N
    assert session.manifest.source["tool_pose"] == "ProbeToTemplate"
    assert session.manifest.source["tool_pose_path"] == "inv(TemplateToStepperHome) @ ProbeToStepperHome"
    assert session.phantom_to_base is None and session.manifest.source["phantom_pose_path"] is None


def test_an_invalid_transform_on_the_path_invalidates_only_its_frame(plus_data, tmp_path):
    rng = np.random.default_rng(15)
    recording = stepper_recording(tmp_path, random_poses(rng, N), probe_valid=np.array([True, True, False, True]),
                                  template_valid=np.array([True, False, True, True]))
    seq = read_sequence(recording)
    session = import_plus(recording, None, tmp_path / "session", reference="Template")
    assert [r.pose_valid for r in session.records] == [True, False, False, True]
    expected = np.linalg.inv(seq.transforms["TemplateToStepperHome"]) @ seq.transforms["ProbeToStepperHome"]
    assert np.allclose(session.poses()[[0, 3]], expected[[0, 3]], atol=1e-9)


def test_cli_tool_pose_option(plus_data, tmp_path):
    rng = np.random.default_rng(16)
    recording = stepper_recording(tmp_path, random_poses(rng, N))
    result = run_cli("import-plus", recording, tmp_path / "session", "--tool-pose", "ProbeToTemplate")
    assert result.returncode == 0, result.stderr
    assert "ProbeToTemplate = inv(TemplateToStepperHome) @ ProbeToStepperHome" in result.stdout
    result = run_cli("import-plus", recording, tmp_path / "home", "--tool-pose", "TemplateToProbe")
    assert result.returncode == 0, result.stderr
    assert "TemplateToProbe = inv(ProbeToStepperHome) @ TemplateToStepperHome" in result.stdout


def test_cli_no_path_exits_2_naming_the_frames_held(plus_data, tmp_path):
    rng = np.random.default_rng(17)
    recording = stepper_recording(tmp_path, random_poses(rng, N))
    for args, asked in (((), "Probe to Reference"), (("--tool-pose", "ProbeToTracker"), "Probe to Tracker"),
                        (("--tool", "Needle"), "Needle to Reference")):
        result = run_cli("import-plus", recording, tmp_path / "out", *args)
        assert_one_line_error(result, "stepper.igs.mha", asked,
                              "the transforms held name the frames Probe, StepperHome, Template")
    for args, fragment in ((("--tool-pose", "ProbeToTemplate", "--reference", "Template"), "not both"),
                           (("--tool-pose", "ProbeToToFCamera"), "give --tool and --reference instead"),
                           (("--tool-pose", "Probe"), "not one <From>To<To> name")):
        assert_one_line_error(run_cli("import-plus", recording, tmp_path / "out", *args), fragment)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stepper.igs.mha"]


def test_phantom_pose_is_composed_through_the_repository(plus_data, tmp_path):
    rng = np.random.default_rng(18)
    holder_to_template = random_poses(rng, 1)[0]
    config = stepper_config(tmp_path, holder_to_template)
    holder_to_phantom = make_transform(np.eye(3), [5, 63.5, 0])  # as the VLCUS device set gives it
    phantom_to_template = holder_to_template @ np.linalg.inv(holder_to_phantom)
    template_to_home = np.tile(random_poses(rng, 1), (N, 1, 1))  # the template does not move
    recording = stepper_recording(tmp_path, template_to_home)

    session = import_plus(recording, config, tmp_path / "template", reference="Template")
    assert session.phantom.n_wires == 6
    assert np.allclose(session.phantom_to_base, phantom_to_template, atol=1e-9)
    assert session.manifest.source["phantom_pose_path"] == "TemplateHolderToTemplate @ inv(TemplateHolderToPhantom)"

    session = import_plus(recording, config, tmp_path / "home", reference="StepperHome")
    seq = read_sequence(recording)
    assert np.allclose(session.poses(), seq.transforms["ProbeToStepperHome"], atol=1e-12)
    assert np.allclose(session.phantom_to_base, seq.transforms["TemplateToStepperHome"][0] @ phantom_to_template,
                       atol=1e-9)
    assert session.manifest.source["phantom_pose_path"] == (
        "TemplateToStepperHome @ TemplateHolderToTemplate @ inv(TemplateHolderToPhantom)")


def test_phantom_that_moves_in_the_reference_frame_has_no_pose(plus_data, tmp_path):
    rng = np.random.default_rng(19)
    config = stepper_config(tmp_path, random_poses(rng, 1)[0])
    recording = stepper_recording(tmp_path, random_poses(rng, N))  # the template moves on the stepper
    session = import_plus(recording, config, tmp_path / "home", reference="StepperHome")
    assert all(r.pose_valid for r in session.records)
    assert session.phantom_to_base is None and session.manifest.source["phantom_pose_path"] is None


@pytest.mark.parametrize("matrix", [np.diag([2.0, 2.0, 2.0, 1.0]), np.diag([0.0, 0.0, 0.0, 1.0])])
def test_phantom_pose_that_is_not_rigid_is_refused(plus_data, tmp_path, matrix):
    config = stepper_config(tmp_path, matrix)
    recording = stepper_recording(tmp_path, np.tile(np.eye(4), (N, 1, 1)))
    result = run_cli("import-plus", recording, "--config", config, tmp_path / "out", "--reference", "Template")
    assert_one_line_error(result, "stepper.xml", "Phantom->Template", "is not a rigid transform")
    assert not (tmp_path / "out").exists()
