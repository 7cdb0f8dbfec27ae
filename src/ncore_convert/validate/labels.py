"""Checks of a camera's labels (NCore's camera-labels component, ``--camera-labels``)."""

from __future__ import annotations

import numpy as np
from ncore.data.v4 import SequenceLoaderV4
from ncore.impl.data.types import LabelCategory

from ncore_convert.transforms.sampling import spread_indices
from ncore_convert.validate.report import Report

#: Labels decoded per label component: the first, the last and evenly spread ones between.
DECODED_SAMPLE = 8


def check_camera_labels(report: Report, loader: SequenceLoaderV4, camera_id: str) -> None:
    """Every label component of ``camera_id``: one label per camera frame, at the frame's end time;
    a sample of ``DECODED_SAMPLE`` decoded through the library has the camera's size; depth is
    finite and >= 0 (0: no measurement)."""
    camera = loader.get_camera_sensor(camera_id)
    frames_end_us = np.sort(camera.frames_timestamps_us[:, 1])
    width, height = (int(v) for v in camera.model_parameters.resolution)
    for labels in loader.query_camera_labels(camera_id):
        descriptor = labels.label_descriptor
        name = f"camera {camera_id}: label {descriptor.default_instance_name}"
        stamps_us = np.sort(labels.label_timestamps_us)
        report.add(
            f"{name}: one per camera frame",
            np.array_equal(stamps_us, frames_end_us),
            f"{len(stamps_us)} labels for {len(frames_end_us)} frames"
            f" ({len(np.setdiff1d(frames_end_us, stamps_us))} frames without one,"
            f" {len(np.setdiff1d(stamps_us, frames_end_us))} labels at no frame's end time)",
        )
        problems, labelled = [], []
        for i in spread_indices(len(stamps_us), DECODED_SAMPLE):
            ts = int(stamps_us[i])
            try:
                data = labels.get_label(ts).get_data()
            except Exception as err:  # noqa: BLE001 - any failure to decode is the finding
                problems.append(f"{ts}: does not decode ({type(err).__name__})")
                continue
            if data.shape[:2] != (height, width):
                problems.append(f"{ts}: {data.shape[1]}x{data.shape[0]} px")
            elif descriptor.label_type.category == LabelCategory.DEPTH and not np.all(np.isfinite(data) & (data >= 0)):
                problems.append(f"{ts}: depth not finite and >= 0 everywhere")
            else:
                labelled.append(float(np.count_nonzero(data)) / data.size)
        report.add(
            f"{name}: decodes, the camera's size, valid values",
            not problems,
            "; ".join(problems[:3])
            or f"{len(labelled)} labels decoded ({width}x{height}), median {np.median(labelled):.2%} of pixels set",
        )
