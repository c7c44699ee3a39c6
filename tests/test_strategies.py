"""The source and the integration as strategies resolved once (mono_map/mapping/strategies.py)."""

import pytest

from mono_map.errors import MonoMapError
from mono_map.mapping.strategies import INTEGRATIONS, SOURCES, integration_of, source_of


def test_each_source_says_what_applies_to_it():
    flags = {name: (s.camera, s.predicted, s.ground_truth, s.fov_only, s.lidar)
             for name, s in ((n, source_of(n)) for n in SOURCES)}
    assert flags == {"mono": (True, True, False, False, False), "depth-gt": (True, False, True, False, False),
                     "lidar": (False, False, False, False, True), "lidar-fov": (False, False, False, True, True)}


def test_only_a_predicted_source_integrates_distributions():
    for name in INTEGRATIONS:
        mono = integration_of(name, "mono")
        assert (mono.distributional, mono.fused, mono.end_points) == (name != "keep", name == "fused", name == "keep")
        for other in ("depth-gt", "lidar", "lidar-fov"):
            it = integration_of(name, source_of(other))
            assert (it.distributional, it.fused, it.end_points) == (False, False, True)


@pytest.mark.parametrize("call, option", [(lambda: source_of("radar"), "--source: unknown source 'radar'"),
                                          (lambda: integration_of("mean", "mono"), "--integrate: unknown integration"),
                                          (lambda: integration_of("keep", "sonar"), "--source: unknown source")])
def test_an_unknown_name_is_one_line_naming_the_option(call, option):
    with pytest.raises(MonoMapError, match=option):
        call()
