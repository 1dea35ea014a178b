"""Tutorial 02, a task of your own: runs top to bottom at tiny sizes (tutorial_runs.py)."""

from tutorial_runs import runs_at_tiny_sizes_as_committed


def test_your_own_task_runs_at_tiny_sizes_and_shows_what_its_full_run_shows():
    runs_at_tiny_sizes_as_committed("02_your_own_task")
