"""Bench section ``ablation``: registered, every row's switch accepted by ``analysis_params`` and changing only what
it names, and the verdict's noise rule (no analysis is run here)."""

import math

import pytest

import skinstretch.experiments.commands.bench as bench_command
from skinstretch.experiments.bench import ablation


def test_the_section_is_registered():
    assert bench_command.available_sections()["ablation"] is ablation


@pytest.mark.parametrize("stage", ablation.STAGES, ids=lambda s: f"{s.method}: {s.name}")
def test_each_switch_is_accepted_and_changes_only_what_it_names(stage):
    on = ablation.stage_params(None).model_dump()
    off = ablation.stage_params(stage).model_dump()
    assert on["execution"]["kind"] == off["execution"]["kind"] == "serial"
    for group, value in stage.switch.items():
        if isinstance(value, dict):
            for name, wanted in value.items():
                assert off[group][name] == wanted
                assert on[group][name] != wanted  # the default has the stage on
                off[group][name] = on[group][name]
        else:
            assert off[group] == value != on[group]
            off[group] = on[group]
    assert off == on


def test_stage_rows_cover_both_methods_and_name_their_switches():
    assert {s.method for s in ablation.STAGES} == set(ablation.METHODS)
    assert len({(s.method, s.name) for s in ablation.STAGES}) == len(ablation.STAGES)
    assert ablation.STAGES[0].switch_text() == "tracking.keyframe_interval_frames=None"


def test_verdict_counts_a_change_only_beyond_the_noise():
    on = {"disp mean": 0.030, "disp worst": 0.040, "edge mean": 0.10, "edge worst": 0.20, "points mean": 100.0}
    assert ablation.stage_verdict(on, dict(on, **{"edge worst": 0.21})) == "within noise"  # 5 % < 10 %
    assert ablation.stage_verdict(on, dict(on, **{"edge worst": 0.25})) == "pays"
    assert ablation.stage_verdict(on, dict(on, **{"disp mean": 0.020})) == "off better"
    assert ablation.stage_verdict(on, dict(on, **{"disp mean": 0.020, "edge mean": 0.2})) == "pays"
    assert ablation.stage_verdict(on, dict(on, **{"edge mean": math.nan})) == "pays"  # nothing measured off
    assert ablation.stage_verdict(on, dict(on, **{"points mean": 80.0})) == "pays"  # a sparser mesh off
    assert ablation.stage_verdict(on, dict(on, **{"points mean": 120.0})) == "within noise"
