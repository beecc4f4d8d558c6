import os

# Headless rendering must be chosen before mujoco is imported anywhere.
os.environ.setdefault("MUJOCO_GL", "egl")


import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

# The suite runs in two worker processes (README): a property's examples are not timed, so that
# a loaded machine cannot fail a test that is correct (hypothesis' default deadline is 200 ms).
settings.register_profile("mbtsr", deadline=None)
settings.load_profile("mbtsr")


@pytest.fixture(autouse=True)
def _planner_costs_stay_interpreted(monkeypatch):
    """Tests plan a few steps: the agent's planner cost is not JIT-compiled (0.1-0.3 s a
    function, 68 compiles in the fast suite). Compiled and interpreted costs give the same bits
    (tests/test_costs.py), so no result depends on it."""
    import agents.planning

    monkeypatch.setattr(agents.planning, "JIT_AFTER", False)
