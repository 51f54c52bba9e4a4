"""``model.spp`` as a schedule ``{spp: first step}`` (:mod:`torchir.training.spp`): the stage of
each step, YAML's string keys, and ``torchir tune``'s refusal (a setting is one spp per run)."""
from __future__ import annotations

import pytest

from torchir.training.spp import SppSchedule
from torchir.tune.space import config_spp


def test_each_step_takes_the_last_stage_started_at_or_before_it():
    schedule = SppSchedule.parse({8: 0, 64: 100, 16: 250})
    assert [schedule.at(s) for s in (0, 99, 100, 249, 250, 10**9)] == [8, 8, 64, 64, 16, 16]
    assert schedule.first == 8 and SppSchedule.parse(4).stages == ((0, 4),)
    assert SppSchedule.parse({"8": 0, " 64": 3}).stages == ((0, 8), (3, 64))  # keys as JSON or --set gives them


@pytest.mark.parametrize("spp", [True, 2.5, "8", {8: 0, "x": 3}, {8: 0, 16: 2.0}, {8: 0, 16: True}])
def test_non_integer_counts_and_steps_are_refused(spp):
    with pytest.raises((TypeError, ValueError), match="model.spp"):
        SppSchedule.parse(spp)


def test_tune_refuses_a_schedule_and_says_how_to_tune_the_config():
    assert config_spp({}) == 8 and config_spp({"spp": 3}) == 3
    with pytest.raises(ValueError, match=r"model.spp is a schedule \{8: 0, 64: 100\}.*spp: 8"):
        config_spp({"spp": {8: 0, 64: 100}})
