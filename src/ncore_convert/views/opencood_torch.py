"""A thin ``torch.utils.data.Dataset`` over :class:`~ncore_convert.views.opencood.OpenCoodScenario`:
item ``i`` is :meth:`~ncore_convert.views.opencood.OpenCoodScenario.base_data` at the OpenCOOD
ego's ``i``-th frame key. Import this module only where torch is installed; nothing else in
ncore-convert imports torch."""

from __future__ import annotations

import torch.utils.data

from ncore_convert.views.opencood import OpenCoodScenario


class OpenCoodBaseDataset(torch.utils.data.Dataset):
    """The base data of every ego frame of one converted scenario (numpy arrays and dicts, as
    OpenCOOD's base dataset hands them to its fusion datasets)."""

    def __init__(self, view: OpenCoodScenario) -> None:
        self.view = view
        self.ego_keys = view.keys(view.ego_agent_id)

    def __len__(self) -> int:
        return len(self.ego_keys)

    def __getitem__(self, index: int) -> dict[str, dict]:
        return self.view.base_data(self.ego_keys[index])
