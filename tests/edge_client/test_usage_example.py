"""The scenario file shown in docs/usage.md is valid and drives inside the operating bounds."""

import re
from pathlib import Path

import numpy as np
import yaml

from edge_client.plant import PlantSimulator
from edge_client.scenario import scenario_from_data
from synth.params import OperatingBounds

USAGE = Path(__file__).parents[2] / "docs" / "usage.md"


def test_readme_scenario_example_loads_and_stays_in_bounds():
    text = USAGE.read_text()
    section = text[text.index("### Scenario files") :]
    block = re.search(r"```yaml\n(.*?)```", section, re.S)
    assert block is not None
    scenario = scenario_from_data(yaml.safe_load(block.group(1)), source="docs/usage.md")
    assert [f.kind for f in scenario.faults] == ["bias", "bias"] and scenario.gusts
    # the other fault kinds quoted inline are valid too
    inline = re.findall(r"`(\{kind: [^`]*\})`", " ".join(section.split()))
    assert len(inline) == 3
    for fault in inline:  # the same drive with each inline fault in turn
        data = scenario.model_dump(mode="json") | {"faults": [yaml.safe_load(fault)]}
        extra = scenario_from_data(data, source="docs/usage.md inline fault")
        assert extra.faults[0].kind in ("loss_of_effectiveness", "sinusoidal", "intermittent")
    plant = PlantSimulator([scenario])
    x = np.array([plant.step().x[0] for _ in range(int(plant.n_samples[0]))])
    b = OperatingBounds()
    assert b.vx_min_mps <= x[:, 0].min() and x[:, 0].max() <= b.vx_max_mps
    assert np.abs(x[:, 1]).max() <= b.vy_max_mps and np.abs(x[:, 2]).max() <= b.r_max_radps
