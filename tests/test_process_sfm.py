"""SfM bookkeeping: which model is kept, and the registration check (pure parts of sfm.py)."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from rainyscape.errors import ConfigError, DataError
from rainyscape.process.sfm import Registration, SfmOptions, check_registration, largest_model


@dataclass
class FakeModel:
    registered: int
    points: int

    def num_reg_images(self) -> int:
        return self.registered

    def num_points3D(self) -> int:  # noqa: N802 - pycolmap's name
        return self.points


def test_largest_model_is_the_one_with_most_frames_not_the_first():
    models = {0: FakeModel(5, 900), 1: FakeModel(12, 300), 2: FakeModel(12, 400)}
    key, model = largest_model(models)
    assert key == 2 and model is models[2]  # ties broken by points
    assert largest_model({}) == (None, None)


def report(registered: int, total: int = 10) -> Registration:
    names = [f"f{i}.png" for i in range(total)]
    return Registration(total=total, registered=names[:registered], unregistered=names[registered:],
                        mean_reprojection_error=0.5, num_points=100, model_sizes=[registered])


def test_registration_check():
    opts = SfmOptions(min_registered=0.5)
    assert check_registration(report(10), opts, "clip.mp4") is None
    warning = check_registration(report(7), opts, "clip.mp4")
    assert "70 %" in warning and "f7.png" in warning and "--num-frames" in warning
    with pytest.raises(DataError, match="only 4 of 10"):
        check_registration(report(4), opts, "clip.mp4")
    with pytest.raises(DataError, match="static"):
        check_registration(report(0), opts, "clip.mp4")


@pytest.mark.parametrize("field, value", [("camera_model", "FISHEYE"), ("matcher", "vocab"),
                                          ("max_features", 10), ("min_registered", 0.0),
                                          ("init_min_tri_angle", 0.0), ("vocab_tree", "/no/such/tree.bin")])
def test_bad_sfm_options(field, value):
    with pytest.raises(ConfigError):
        SfmOptions(**{field: value}).validate()


def test_report_lists_each_mapping_tried():
    from rainyscape.process.sfm import mapping_attempt

    first, second = report(8), report(9)
    second.attempts = [mapping_attempt("default", first, False), mapping_attempt("relaxed", second, True)]
    assert second.to_json()["attempts"][1] == {"mapper": "relaxed", "registered": 9,
                                               "mean_reprojection_error_px": 0.5, "num_points": 100,
                                               "kept": True}
    assert "default mapping: 8, relaxed mapping: 9 (kept)" in second.summary()
    assert "mapping:" not in report(10).summary()  # one attempt: nothing to say


def test_deterministic_means_one_thread_in_every_pose_step():
    from rainyscape.process.sfm import SfmOptions

    assert SfmOptions(num_threads=8).threads == 8
    assert SfmOptions(num_threads=8, deterministic=True).threads == 1
