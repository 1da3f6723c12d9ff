"""Where the PLUS toolkit's public test recordings are, for the real-data tests and benchmarks.

One setting: the folder named by the environment variable ``PROBECAL_PLUS_DATA``, by default
``../shared/data/plus`` beside this repository. The files are those of the public
PlusToolkit/PlusLibData repository at ``COMMIT``, in its layout; ``python -m core.io.plusdata``
prints their paths (the README's "Real data" section fetches them with git).
"""

from __future__ import annotations

import os
from pathlib import Path

ENV = "PROBECAL_PLUS_DATA"
DEFAULT = Path(__file__).resolve().parents[3] / "shared" / "data" / "plus"  # beside a checkout
REPOSITORY = "https://github.com/PlusToolkit/PlusLibData.git"
COMMIT = "51dcbb76d9f29fad94cf80788a7a0b7c704fb5dc"
FILES = (
    "CADModels/Probe_L14-5_38_lowres.stl",
    "CADModels/fCal_1.2.stl",
    "ConfigFiles/PlusDeviceSet_Server_Sim_NwirePhantom.xml",
    "ConfigFiles/PlusDeviceSet_fCal_Sim_TemporalCalibration.xml",
    "ConfigFiles/Testing/PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml",
    "ConfigFiles/Testing/PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_LN_MAXI.xml",
    "ConfigFiles/Testing/PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml",
    "ConfigFiles/Testing/PlusDeviceSet_fCal_Sim_SpatialCalibration_1.2.xml",
    "ConfigFiles/Testing/PlusDeviceSet_iCal_CalibrationOnly_FrameGrabber.xml",
    "ConfigFiles/Testing/PlusDeviceSet_iCal_CalibrationOnly_VLCUS_FrameGrabber.xml",
    "TestImages/FreehandCalibration3NWires.results.xml",
    "TestImages/NwirePhantomFreehand.igs.mha",
    "TestImages/NwirePhantomFreehandReconstructed.mha",
    "TestImages/SegmentationTest_VLCUS_RandomStepperMotionData2.igs.mha",
    "TestImages/SegmentationTest_VLCUS_RandomStepperMotionData2_Segmentation_baseline.xml",
    "TestImages/SpinePhantomFreehand.igs.mha",
    "TestImages/TemporalCalibrationResultsBaseline.xml",
    "TestImages/USTC_FrameGrabber_ProbeRotationData.igs.mha",
    "TestImages/USTC_FrameGrabber_ProbeRotationData_Segmentation_baseline.xml",
    "TestImages/WaterTankBottomTranslationTrackerBuffer-trimmed.igs.mha",
    "TestImages/WaterTankBottomTranslationVideoBuffer.igs.mha",
    "TestImages/fCal_Test_Calibration_3NWires.igs.mha",
    "TestImages/fCal_Test_Validation_3NWires.igs.mha",
    "TestImages/vtkVolumeReconstructorTestLNMAXIvolumeRef.mha",
    "TestImages/vtkVolumeReconstructorTestNNMEANvolumeRef.mha",
)
"""The PlusLibData files probecal's tests and benchmarks read."""


def plus_data_dir() -> Path:
    """The PLUS data folder the setting names (it may not exist)."""
    value = os.environ.get(ENV)
    return Path(value).expanduser() if value else DEFAULT


def missing_reason() -> str | None:
    """Why the PLUS data cannot be used, naming the setting and the first missing file, or None
    when every file is there."""
    folder = plus_data_dir()
    missing = [name for name in FILES if not (folder / name).is_file()]
    if not missing:
        return None
    setting = f"{ENV}={folder}" if os.environ.get(ENV) else f"{ENV} unset, so {folder}"
    what = "has none of its files" if len(missing) == len(FILES) else f"lacks {len(missing)} files ({missing[0]} first)"
    return f"real PLUS data: {setting} {what}; see the README, 'Real data'"


if __name__ == "__main__":
    print("\n".join(FILES))
