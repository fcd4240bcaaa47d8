"""A calibration asked for through the API fits what automatic calibrations and the harness
fit: the API's defaults are the fit's own (they once said 64 VLAD words against 128)."""

from __future__ import annotations

from service.api.schemas_admin import JobIn
from service.jobs.calibration import calibration_config
from service.ml.calibration import CalibrationConfig


def test_an_api_calibration_with_defaults_is_the_automatic_calibration() -> None:
    params = JobIn(kind="calibrate").job_params()
    config = calibration_config(params)
    assert config == CalibrationConfig()
    assert config.words_for(128) == 128  # DISK: 16,384 values of VLAD
    assert config.words_for(64) == 256  # XFeat


def test_an_api_calibration_can_still_choose_its_vocabulary() -> None:
    params = JobIn.model_validate({"kind": "calibrate", "calibration": {"words": 64}}).job_params()
    assert calibration_config(params).words_for(128) == 64
