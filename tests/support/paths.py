"""Where the checkout is and the real PLUS recordings the tests read (``PROBECAL_PLUS_DATA``,
core/io/plusdata.py): tests that need them take the ``plus_data`` fixture, which skips without them."""

from __future__ import annotations

from pathlib import Path

from probecal.core.io.plusdata import plus_data_dir

ROOT = Path(__file__).resolve().parent.parent.parent
PLUS = plus_data_dir()
FCAL_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_fCal_Sim_SpatialCalibration_1.2.xml"
FCAL_CALIBRATION = PLUS / "TestImages" / "fCal_Test_Calibration_3NWires.igs.mha"
FCAL_VALIDATION = PLUS / "TestImages" / "fCal_Test_Validation_3NWires.igs.mha"
FCAL_RESULTS = PLUS / "TestImages" / "FreehandCalibration3NWires.results.xml"
VLCUS_CONFIG = PLUS / "ConfigFiles" / "Testing" / "PlusDeviceSet_iCal_CalibrationOnly_VLCUS_FrameGrabber.xml"
