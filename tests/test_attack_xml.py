"""Hostile XML: PLUS device sets (read for calibrations, phantoms and imports), fCal results and
segmentation baselines with short, non-numeric or non-finite matrices and attributes, singular or
non-rigid transforms, missing elements and malformed or explosive XML are refused with InputError
naming the file and the element."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from probecal.core.calibration.result import load_calibration
from probecal.core.io.deviceset import read_device_set
from probecal.core.io.phantomfile import load_phantom
from probecal.core.io.plusresults import read_calibration_results, read_segmentation_baseline
from tests.support.cli import run_cli
from tests.support.refusals import assert_one_line_error, assert_refused

IDENTITY = "1 0 0 0  0 1 0 0  0 0 1 0  0 0 0 1"
FIELDS = {
    "image_probe": "0 0.1 0 10  -0.1 0 0 20  0 0 0.1 30  0 0 0 1",
    "phantom_reference": "0 -1 0 5  1 0 0 6  0 0 1 7  0 0 0 1",
    "spacing": "0.078",
    "origin": "27 27",
    "size": "766 562",
    "bar": "2.0",
    "front": "0 0 0",
    "back": "0 40 0",
    "landmark": "10 20 0",
}
DEVICE_SET = """<?xml version="1.0" encoding="utf-8"?>
<PlusConfiguration version="2.1">
  <DataCollection><DeviceSet Name="attack" Description="hostile input" /></DataCollection>
  <CoordinateDefinitions>
    <Transform From="Image" To="Probe" Matrix="{image_probe}" />
    <Transform From="Phantom" To="Reference" Matrix="{phantom_reference}" />
  </CoordinateDefinitions>
  <Segmentation ApproximateSpacingMmPerPixel="{spacing}" ClipRectangleOrigin="{origin}"
    ClipRectangleSize="{size}" MorphologicalOpeningBarSizeMm="{bar}" />
  <PhantomDefinition>
    <Description Name="attack" />
    <Geometry>
      <Pattern Type="NWire">
        <Wire Name="1:left" EndPointFront="{front}" EndPointBack="{back}" />
        <Wire Name="2:diagonal" EndPointFront="20 0 0" EndPointBack="0 40 0" />
        <Wire Name="3:right" EndPointFront="20 0 0" EndPointBack="20 40 0" />
      </Pattern>
      <Landmarks><Landmark Name="#1" Position="{landmark}" /></Landmarks>
    </Geometry>
  </PhantomDefinition>
</PlusConfiguration>
"""
MATRIX_FIELDS = {"image_probe": "Transform Image->Probe", "phantom_reference": "Transform Phantom->Reference"}
VECTOR_FIELDS = {"front": "wire 1:left EndPointFront", "back": "wire 1:left EndPointBack",
                 "landmark": "landmark Position"}
HINT_FIELDS = {"spacing": "ApproximateSpacingMmPerPixel", "origin": "ClipRectangleOrigin",
               "size": "ClipRectangleSize", "bar": "MorphologicalOpeningBarSizeMm"}
NOT_NUMBERS = {
    "letters": "a b c",
    "hex": "0x10",
    "comma": "1,2",
    "nan": "nan",
    "inf": "inf",
    "overflow": "1e999",
    "huge integer": "9" * 5000,
}


def device_set(tmp_path: Path, name: str = "set.xml", **fields: str) -> Path:
    path = tmp_path / name
    path.write_text(DEVICE_SET.format(**(FIELDS | fields)))
    return path


def refused(load, path: Path, *fragments: str) -> str:
    """``load(path)`` raises InputError naming ``path`` and every fragment, on one line."""
    return assert_refused(lambda: load(path), path, *fragments)


def test_valid_device_set_loads(tmp_path):
    path = device_set(tmp_path)
    config = read_device_set(path)
    assert config.name == "attack" and config.phantom.n_wires == 3
    assert config.segmentation.clip_origin_px == (27, 27) and config.segmentation.approximate_spacing_mm == 0.078
    calibration = load_calibration(path)
    assert calibration.pixel_spacing_mm == pytest.approx((0.1, 0.1))
    assert np.allclose(calibration.phantom_to_base[:3, 3], [5, 6, 7])
    assert load_phantom(path).n_wires == 3


@pytest.mark.parametrize("field", sorted(MATRIX_FIELDS))
@pytest.mark.parametrize(
    "matrix, fragment",
    [
        ("", "needs 16 numbers, got 0"),
        (" ".join(["1"] * 15), "needs 16 numbers, got 15"),
        (" ".join(["1"] * 17), "needs 16 numbers, got 17"),
        (IDENTITY.replace("0 0 0 1", "0 0 1 1"), "last row must be 0 0 0 1"),
        (IDENTITY[:-1] + "2", "last row must be 0 0 0 1"),
        *((IDENTITY.replace("1", text, 1), "Matrix") for text in NOT_NUMBERS.values()),
    ],
)
def test_device_set_matrix_that_is_not_16_finite_numbers(tmp_path, field, matrix, fragment):
    path = device_set(tmp_path, **{field: matrix})
    refused(read_device_set, path, MATRIX_FIELDS[field], fragment)
    refused(load_calibration, path, MATRIX_FIELDS[field])


@pytest.mark.parametrize("field", sorted(VECTOR_FIELDS))
@pytest.mark.parametrize("text", ["", "1 2", "1 2 3 4", *NOT_NUMBERS.values()])
def test_device_set_point_that_is_not_3_finite_numbers(tmp_path, field, text):
    refused(load_phantom, device_set(tmp_path, **{field: text}), VECTOR_FIELDS[field])


@pytest.mark.parametrize("field", sorted(HINT_FIELDS))
@pytest.mark.parametrize("text", ["1 2 3", "-1", "0", "1.5 2", *NOT_NUMBERS.values()])
def test_device_set_segmentation_attribute_of_the_wrong_type(tmp_path, field, text):
    refused(read_device_set, device_set(tmp_path, **{field: text}), f"Segmentation.{HINT_FIELDS[field]}")


@pytest.mark.parametrize(
    "edit, fragment",
    [
        (lambda t: t.replace(' Matrix="0 -1 0 5', ' Other="0 -1 0 5'),
         "Transform Phantom->Reference Matrix is missing"),
        (lambda t: t.replace('From="Image" ', ""), "lacks From or To"),
        (lambda t: t.replace('Type="NWire"', 'Type="CIRS"'), "unsupported type 'CIRS'"),
        (lambda t: t.replace('<Wire Name="2:diagonal" EndPointFront="20 0 0" EndPointBack="0 40 0" />', ""),
         "has 2 wires, an N needs 3"),
        (lambda t: t.replace('2:diagonal" EndPointFront="20 0 0"', '2:diagonal" EndPointFront="0 0 0"'),
         "diagonal is parallel"),
        (lambda t: t.replace("<PlusConfiguration", "<Configuration").replace("</PlusConfiguration", "</Configuration"),
         "not a PLUS device-set file"),
    ],
)
def test_device_set_with_missing_or_wrong_elements(tmp_path, edit, fragment):
    path = tmp_path / "set.xml"
    path.write_text(edit(DEVICE_SET.format(**FIELDS)))
    refused(read_device_set, path, fragment)


ENTITY_BOMB = ('<?xml version="1.0"?><!DOCTYPE l [<!ENTITY a "aaaaaaaaaa">'
               + "".join(f'<!ENTITY {b} "{("&" + a + ";") * 10}">' for a, b in zip("abcdefgh", "bcdefghi"))
               + ']><PlusConfiguration><CoordinateDefinitions><Transform From="Image" To="Probe" Matrix="&i;"/>'
               "</CoordinateDefinitions></PlusConfiguration>")
EXTERNAL_ENTITY = ('<?xml version="1.0"?><!DOCTYPE l [<!ENTITY x SYSTEM "file:///etc/passwd">]>'
                   '<PlusConfiguration><DeviceSet Name="&x;"/></PlusConfiguration>')


@pytest.mark.parametrize(
    "text",
    [
        "",
        "<PlusConfiguration>",
        "<PlusConfiguration><CoordinateDefinitions></PlusConfiguration>",
        DEVICE_SET.format(**FIELDS)[:400],
        "\x00\x01binary",
        ENTITY_BOMB,
        EXTERNAL_ENTITY,
    ],
)
def test_malformed_or_explosive_xml(tmp_path, text):
    path = tmp_path / "bad.xml"
    path.write_text(text)
    refused(read_device_set, path, "not valid XML")
    refused(load_calibration, path, "not valid XML")


def test_deeply_nested_xml_is_read_without_recursion(tmp_path):
    path = tmp_path / "deep.xml"
    path.write_text("<PlusConfiguration>" + "<a>" * 100_000 + "</a>" * 100_000 + "</PlusConfiguration>")
    assert read_device_set(path).transforms == {}
    refused(load_calibration, path, "no Image->Probe transform")


@pytest.mark.parametrize(
    "fields, fragment",
    [
        ({"phantom_reference": "0 0 0 5  0 0 0 6  0 0 0 7  0 0 0 1"}, "Phantom->Reference is not a rigid"),
        ({"phantom_reference": "2 0 0 5  0 2 0 6  0 0 2 7  0 0 0 1"}, "Phantom->Reference is not a rigid"),
        ({"image_probe": "0.1 0.1 0 10  0 0 0 20  0 0 0.1 30  0 0 0 1"}, "from perpendicular"),
        ({"image_probe": "0 0.1 0 10  0 0 0 20  0 0 0.1 30  0 0 0 1"}, "zero"),
        ({"image_probe": "0 0 0 0  0 0 0 0  0 0 0 0  0 0 0 1"}, "zero"),
        ({"image_probe": "1e300 0 0 0  0 1e300 0 0  0 0 1 0  0 0 0 1"}, "overflowing"),
    ],
)
def test_device_set_transform_unfit_for_a_calibration(tmp_path, fields, fragment):
    refused(load_calibration, device_set(tmp_path, **fields), fragment)


def test_singular_transform_is_not_inverted(tmp_path):
    text = DEVICE_SET.format(**FIELDS).replace('From="Phantom" To="Reference"', 'From="Reference" To="Phantom"')
    path = tmp_path / "set.xml"
    path.write_text(text.replace(FIELDS["phantom_reference"], "0 0 0 5  0 0 0 6  0 0 0 7  0 0 0 1"))
    refused(load_calibration, path, "Transform Reference->Phantom is singular")
    path.write_text(text.replace('From="Image" To="Probe"', 'From="Probe" To="Image"')
                    .replace(FIELDS["image_probe"], "1 0 0 0  1 0 0 0  0 0 0 0  0 0 0 1"))
    refused(load_calibration, path, "Transform Probe->Image is singular")


@pytest.mark.parametrize("matrix", ["", "1 2 3", "a " * 16, "nan " + "0 " * 15, IDENTITY.replace("0 0 0 1", "1 0 0 1")])
def test_bare_transform_element(tmp_path, matrix):
    path = tmp_path / "element.xml"
    path.write_text(f'<Transform From="Image" To="Probe" Matrix="{matrix}" />')
    refused(load_calibration, path, "Transform Image->Probe Matrix")


# fCal's results and PLUS's segmentation baselines.

RESULTS = {
    "matrix": "0 0.1 0 10  -0.1 0 0 20  0 0 0.1 30  0 0 0 1",
    "mean": "1.2",
    "position": "584.5 286.8 0",
    "probe": IDENTITY,
}
RESULTS_XML = """<ProbeCalibrationResult version="2.0">
  <CalibrationResults><Transform From="Image" To="Probe" Matrix="{matrix}" /></CalibrationResults>
  <ErrorReport>
    <ReprojectionError3DStatistics ValidationMeanMm="{mean}" ValidationStdDevMm="0.5" CalibrationMeanMm="1.1"
      CalibrationStdDevMm="0.5" />
    <ValidationData>
      <Frame Index="0" SegmentationStatus="OK">
        <SegmentedPoints>
          <Point WireName="1" Position="{position}" /><Point WireName="2" Position="1 2 0" />
        </SegmentedPoints>
        <CustomFrameField Name="ProbeToTrackerTransform" Value="{probe}" />
        <CustomFrameField Name="ReferenceToTrackerTransform" Value="{reference}" />
      </Frame>
    </ValidationData>
    <CalibrationData />
  </ErrorReport>
</ProbeCalibrationResult>
"""


def results(tmp_path: Path, **fields: str) -> Path:
    path = tmp_path / "fcal.results.xml"
    path.write_text(RESULTS_XML.format(**({"reference": IDENTITY} | RESULTS | fields)))
    return path


def test_valid_results_load(tmp_path):
    loaded = read_calibration_results(results(tmp_path))
    assert loaded.pre3d_validation_mm == (1.2, 0.5) and loaded.calibration == []
    assert np.allclose(loaded.validation[0].points, [[584.5, 286.8], [1, 2]])
    assert np.allclose(loaded.validation[0].probe_to_reference, np.eye(4))


@pytest.mark.parametrize(
    "fields, fragment",
    [
        ({"matrix": "1 2 3"}, "CalibrationResults Transform Matrix needs 16"),
        ({"matrix": "nan " * 16}, "CalibrationResults Transform Matrix"),
        ({"mean": ""}, "ReprojectionError3DStatistics ValidationMeanMm needs 1"),
        ({"mean": "low"}, "ReprojectionError3DStatistics ValidationMeanMm"),
        ({"mean": "inf"}, "ReprojectionError3DStatistics ValidationMeanMm"),
        ({"mean": "1 2"}, "ReprojectionError3DStatistics ValidationMeanMm"),
        ({"position": "584.5"}, "ValidationData frame 1 point 1 Position needs 2 or 3"),
        ({"position": "1 2 3 4"}, "ValidationData frame 1 point 1 Position needs 2 or 3"),
        ({"position": "x y"}, "ValidationData frame 1 point 1 Position"),
        ({"position": "1e999 0"}, "ValidationData frame 1 point 1 Position"),
        ({"probe": "1 0 0"}, "ValidationData frame 1 ProbeToTrackerTransform needs 16"),
        ({"probe": IDENTITY.replace("1", "3", 1)}, "ProbeToTrackerTransform is not a rigid"),
        ({"reference": "0 " * 16}, "ReferenceToTrackerTransform is not a rigid"),
    ],
)
def test_results_with_bad_attributes(tmp_path, fields, fragment):
    refused(read_calibration_results, results(tmp_path, **fields), fragment)


def test_results_with_missing_elements(tmp_path):
    path = tmp_path / "r.xml"
    path.write_text(RESULTS_XML.format(reference=IDENTITY, **RESULTS).replace(' ValidationStdDevMm="0.5"', ""))
    refused(read_calibration_results, path, "ValidationStdDevMm is missing")
    path.write_text("<ProbeCalibrationResult />")
    refused(read_calibration_results, path, "not a PLUS probe calibration result")
    path.write_text(RESULTS_XML.format(reference=IDENTITY, **RESULTS).replace(' Matrix="', ' Matrx="'))
    refused(read_calibration_results, path, "Matrix is missing")


@pytest.mark.parametrize("points", ["1 2 3", "a b", "nan 1", "1 inf", "1," * 4])
def test_segmentation_baseline_with_bad_points(tmp_path, points):
    path = tmp_path / "baseline.xml"
    path.write_text(f'<TestResults><TestCase id="0"><Output SegmentationSuccess="1" SegmentationPoints="{points}" />'
                    "</TestCase></TestResults>")
    refused(read_segmentation_baseline, path, "test case 1 SegmentationPoints")


# Through the command line: exit code 2, one line naming the file, nothing written.


def test_cli_validate_refuses_a_nan_phantom_pose(tmp_path):
    bad = device_set(tmp_path, phantom_reference=FIELDS["phantom_reference"].replace("5", "nan"))
    out = tmp_path / "metrics.json"
    result = run_cli("validate", tmp_path, "--calibration", bad, "--out", out)
    assert_one_line_error(result, str(bad), "Transform Phantom->Reference Matrix", "not finite")
    assert not out.exists()


def test_cli_import_refuses_a_short_matrix_before_reading_the_sequence(tmp_path):
    bad = device_set(tmp_path, image_probe="1 0 0 0")
    out = tmp_path / "imported"
    result = run_cli("import-plus", tmp_path / "absent.igs.mha", "--config", bad, out)
    assert_one_line_error(result, str(bad), "Transform Image->Probe Matrix needs 16 numbers")
    assert not out.exists() and not any(p.name.startswith(".imported") for p in tmp_path.iterdir())
