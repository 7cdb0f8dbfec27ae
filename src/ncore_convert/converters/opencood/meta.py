"""OPV2V / V2XSet: what a converted scenario says of itself: each sequence's generic metadata, and
``scenario.json`` (how the scenario's agents and sequences relate, and what was left out)."""

from __future__ import annotations

from dataclasses import asdict

from ncore_convert import contract
from ncore_convert.contract import ManifestAgent, ManifestNoise, ScenarioManifest
from ncore_convert.converters import consumer
from ncore_convert.converters.opencood.records import Names, OpenCoodOptions, ScenarioPlan
from ncore_convert.sources import opencood as src


def generic_meta(plan: ScenarioPlan, agent_ids: list[str], names: dict[str, Names], world_global_meta: dict) -> dict:
    """The sequence metadata of ``agent_ids``' sequence (``names``: their frame and sensor names)."""
    meta = {
        contract.SOURCE_DATASET: plan.options.dataset,
        contract.OPENCOOD_SPLIT: plan.options.split,
        contract.SCENARIO: plan.scenario,
        contract.AGENTS: {a: {"kind": plan.agents[a].kind, "opencood_ego": a == plan.ego} for a in agent_ids},
        "carla_fixed_delta_seconds": plan.fixed_delta_seconds,
        contract.OPENCOOD_PROTOCOL: plan.protocol_text,
        "time_base": "t_us = CARLA frame key * fixed_delta_seconds * 1e6 (frame keys are CARLA frame counters)",
        contract.WORLD_GLOBAL: world_global_meta,
        "noise_settings": {s.name: s.as_dict() for s in plan.options.noise},
        contract.CONVERTER: contract.converter_meta(_options_meta(plan.options)),
    }
    left_out = {names[a].sensor(s): why for a in agent_ids for s, why in plan.agents[a].sensors_not_written.items()}
    if left_out:  # only then: a healthy scenario's sequences stay as they were
        meta[contract.SENSORS_NOT_WRITTEN] = left_out
    if plan.window_us is not None:
        meta[contract.CLIP] = consumer.clip_meta(plan.options, plan.window_us)
    return meta


def _options_meta(options: OpenCoodOptions) -> dict:
    """The conversion options as metadata (the noise settings are listed on their own)."""
    out = asdict(options)
    out["noise"] = [s.name for s in options.noise]
    return out


def _manifest_agent(plan: ScenarioPlan, agent_id: str) -> ManifestAgent:
    agent = plan.agents.get(agent_id)
    base = {"agent_id": int(agent_id), "kind": src.agent_kind(agent_id), "opencood_ego": agent_id == plan.ego}
    if agent is None:
        return ManifestAgent(**base, written=False, not_written=plan.agents_not_written.get(agent_id))
    scenario_layout = plan.options.layout == "scenario"
    return ManifestAgent(
        **base,
        written=True,
        frames=len(agent.keys),
        sensors=agent.lidar_ids + agent.camera_ids,
        sequence=None if scenario_layout else f"{agent_id}/{plan.sequence_id(agent_id)}.json",
        frame_prefix=contract.agent_prefix(agent_id) if scenario_layout else None,
        not_written=agent.sensors_not_written or None,
    )


def manifest(plan: ScenarioPlan) -> ScenarioManifest:
    """``scenario.json``: how the scenario's agents and sequences relate."""
    return ScenarioManifest(
        scenario=plan.scenario,
        dataset=plan.options.dataset,
        split=plan.options.split,
        layout=plan.options.layout,
        sequence=f"{plan.scenario}.json" if plan.options.layout == "scenario" else None,
        world_global="CARLA map frame, right-handed: (x, y, z)_world_global = (x, -y, z)_carla (all agents)"
        if plan.options.world_global_mode == "localized"
        else f"world_global_mode {plan.options.world_global_mode}: each sequence's metadata world_global"
        ".T_world_dataset_global places its world in the right-handed CARLA map frame",
        fixed_delta_seconds=plan.fixed_delta_seconds,
        time_base="t_us = CARLA frame key * fixed_delta_seconds * 1e6",
        ego_agent_id=int(plan.ego),
        ego_rule="OpenCOOD: first agent folder by string sort, infrastructure last",
        agents=[_manifest_agent(plan, agent_id) for agent_id in plan.agent_folders],
        noise_settings=[ManifestNoise(s.name, s.model, s.seed, poses_instance=s.name) for s in plan.options.noise],
        labels="union of every agent's vehicle labels per tick (each agent labels vehicles it hit with >= 1"
        " semantic-lidar ray within 120 m) plus the CAVs' own boxes; not complete scene ground truth",
    )
