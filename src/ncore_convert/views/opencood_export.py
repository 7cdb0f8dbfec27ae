"""``export-opencood``: a converted cooperative scenario written back in OpenCOOD's on-disk layout,
so that unmodified OpenCOOD code trains on it:

```
<out>/<scenario>/data_protocol.yaml
<out>/<scenario>/<agent_id>/<key>.yaml | <key>.pcd | <key>_camera<k>.png
```

Everything comes from :class:`~ncore_convert.views.opencood.OpenCoodScenario`. What the
conversion left out (an unreadable sensor, an agent) is left out here too and listed in
``ExportCounts.left_out``; an agent whose lidar was not written is not exported. The PCDs are
Open3D-style ASCII with the intensity in the red byte of ``rgb``; the YAMLs and PNGs are the stored
ones as they were, except that with a noise setting each YAML is rewritten with that setting's
``lidar_pose`` (switch OpenCOOD's own ``wild_setting`` off then, or the noise is applied twice).
The scenario is written to ``<out>/.<scenario>.partial`` and renamed into place when complete.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import yaml
from upath import UPath

from ncore_convert.sources.pcd import write_pcd
from ncore_convert.storage import publish, remove_tree
from ncore_convert.views.opencood import OpenCoodScenario


@dataclass
class ExportCounts:
    agents: int = 0
    frames: int = 0
    points: int = 0
    images: int = 0
    left_out: list[str] = field(default_factory=list)  #: what is not in the export, and why, a line each

    def line(self, scenario_dir: UPath) -> str:
        return f"{scenario_dir}: {self.agents} agents, {self.frames} frames, {self.points} points, {self.images} images"


def export_opencood(
    manifest_path: UPath, out_dir: UPath, poses: str | None = None, progress: Callable[[int], None] = lambda n: None
) -> tuple[UPath, ExportCounts]:
    """Write the scenario of ``manifest_path`` (its ``scenario.json``) under ``out_dir`` in OpenCOOD's
    layout, with the poses of noise setting ``poses`` (None: the ground truth). Returns the scenario
    folder and what was written; ``progress(n)`` is told of each agent-frame."""
    view = OpenCoodScenario.open(manifest_path, poses)
    final = UPath(out_dir) / view.manifest.scenario
    work = UPath(out_dir) / f".{view.manifest.scenario}.partial"
    remove_tree(work)
    work.mkdir(parents=True)
    if view.protocol_text is not None:  # a scenario without one gets none back
        (work / "data_protocol.yaml").write_text(view.protocol_text)
    counts = ExportCounts(left_out=view.left_out())
    for agent_id in view.agent_ids:
        if not view.has_lidar(agent_id):  # OpenCOOD reads an agent-frame by its PCD
            counts.left_out.append(f"agent {agent_id}: not exported: OpenCOOD reads each agent-frame by its PCD")
            continue
        agent_dir = work / agent_id
        agent_dir.mkdir()
        counts.agents += 1
        for key in view.keys(agent_id):
            points = view.lidar_points(agent_id, key)
            _, _, _, field, data = view.pcd_layout(agent_id, key).split()
            if field == "rgb":  # the intensity back to the red byte it came from
                intensity = np.round(points[:, 3].astype(np.float64) * 255.0).astype(np.uint8)
            else:
                intensity = points[:, 3]
            write_pcd(agent_dir / f"{key}.pcd", points[:, :3], intensity, field, binary=data == "binary")
            (agent_dir / f"{key}.yaml").write_text(_yaml_text(view, agent_id, key))
            for index, png in view.images(agent_id, key).items():
                (agent_dir / f"{key}_camera{index}.png").write_bytes(png)
                counts.images += 1
            counts.frames += 1
            counts.points += len(points)
            progress(1)
    publish(work, final)
    return final, counts


def _yaml_text(view: OpenCoodScenario, agent_id: str, key: str) -> str:
    """The frame's YAML: as stored, or with the noise setting's ``lidar_pose`` (dumped again)."""
    if view.poses is None:
        return view.stored_yaml_text(agent_id, key)
    return yaml.safe_dump(view.params(agent_id, key), sort_keys=False)
