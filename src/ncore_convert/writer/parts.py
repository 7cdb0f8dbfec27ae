"""How a log's writing splits into jobs that never share a component store (the ``--profile``
decides the stores), so that each part is written by its own
:class:`~ncore_convert.writer.SequenceWriter` and process."""

from __future__ import annotations

from dataclasses import dataclass

from ncore.impl.data.v4.types import ComponentGroupAssignments

from ncore_convert.contract import Profile


@dataclass(frozen=True)
class WriteJob:
    """One writing job: the base components (poses, intrinsics, masks, cuboids), or the frames of
    the sensors ``sensor_ids`` and the camera labels ``label_ids`` (component instance names)."""

    sensor_ids: tuple[str, ...] = ()
    base: bool = False
    label_ids: tuple[str, ...] = ()


BASE_JOB = WriteJob(base=True)


def independent_parts(
    jobs: list[WriteJob], camera_ids: list[str], lidar_ids: list[str], profile: Profile, label_ids: list[str] = ()
) -> list[list[int]]:
    """Group jobs so that no two groups write to the same component store.

    Returns:
        lists of job indices; each list can be written by its own :class:`SequenceWriter` (and
        process). With ``profile="default"`` everything shares one store, so there is one group.
    """
    groups = component_groups(camera_ids, lidar_ids, profile, label_ids)
    base_groups = {
        groups.poses_component_group,
        groups.intrinsics_component_group,
        groups.masks_component_group,
        groups.cuboid_track_observations_component_group,
    }
    sensor_group = {**groups.camera_component_groups, **groups.lidar_component_groups}
    parts: list[tuple[set, list[int]]] = []
    for index, job in enumerate(jobs):
        touched = set(base_groups) if job.base else {sensor_group.get(sensor) for sensor in job.sensor_ids}
        touched |= {groups.camera_labels_component_groups.get(label) for label in job.label_ids}
        overlapping = [part for part in parts if part[0] & touched]
        merged = (touched.union(*(p[0] for p in overlapping)), sorted([index] + [i for p in overlapping for i in p[1]]))
        parts = [part for part in parts if not part[0] & touched] + [merged]
    return sorted((indices for _, indices in parts), key=lambda indices: indices[0])


def component_groups(
    camera_ids: list[str], lidar_ids: list[str], profile: Profile, label_ids: list[str] = ()
) -> ComponentGroupAssignments:
    return ComponentGroupAssignments.create(
        camera_ids=camera_ids,
        lidar_ids=lidar_ids,
        radar_ids=[],
        point_clouds_ids=[],
        camera_labels_ids=list(label_ids),
        profile=profile,
    )
