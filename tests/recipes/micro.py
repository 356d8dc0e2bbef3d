"""The quick profile, smaller still: the settings the end-to-end recipe tests run with."""

START_STATES = 2

#: Overrides of a micro run of the Pusher recipe (every stage, seconds each).
MICRO = (
    "profile=quick",
    "threads=1",
    "stage_workers=1",  # the worker processes have their own test (test_stage_workers.py)
    "progress=false",
    "data.scripted_episodes=3",
    "data.random_episodes=2",
    "train.max_steps=20",
    "train.val_every=10",
    "agent.mpc_episodes=1",
    "agent.eval_episodes=1",
    "agent.distill.epochs=5",
    f"assess.start_states={START_STATES}",
    "assess.horizon_s=2.0",
    "assess.surface_deadlines_s=[1.0,2.0]",
)

#: Overrides of a micro run of the point-mass recipe.
POINT_MASS_MICRO = (
    "profile=quick",
    "threads=1",
    "progress=false",
    "data.episodes=4",
    "train.max_steps=20",
    "assess.start_states=2",
    "task.deadline_s=1.0",
)


def broken_table_rows(markdown: str) -> list[str]:
    """The rows of ``markdown``'s tables whose cell count differs from their header's (a bare
    ``|`` inside a cell, e.g. in a check named ``|forecast - real| <= 0.10``, adds cells)."""
    import re

    broken, width = [], None
    for line in markdown.splitlines():
        if not line.startswith("|"):
            width = None
            continue
        cells = len(re.findall(r"(?<!\\)\|", line))
        if width is None:
            width = cells
        elif cells != width:
            broken.append(line)
    return broken
