"""The example part type of the simulated station, shipped in the package (``examples/forging/``): the
part file and cold nominal mesh of ``presets.forging_scene()``'s forging, as
:func:`services.simulation.hot_part.write_forging_part` makes them (the one home of that part).

``thermofield demo`` uploads it as a part type, so that its scan ends with a verdict; the README's tour
inspects against it; tests/simulation/test_forging_part.py checks that the shipped files are the ones
``write_forging_part`` makes.
"""

from __future__ import annotations

from pathlib import Path

EXAMPLE_DIRECTORY = Path(__file__).parent / "examples" / "forging"
PART_FILE = EXAMPLE_DIRECTORY / "part.json"
