"""--workers beyond the cores: said, with what runs (gtforge.infra.scheduling)."""


def test_more_workers_than_cores_is_said_once_with_what_runs():
    """--workers beyond the cores (a typo's 100000 starts one process a task): said with the processes that run."""
    from gtforge.infra.scheduling import oversubscription_warning

    assert oversubscription_warning(None, 8, 2) is None  # the default: one per core, capped by the tasks
    assert oversubscription_warning(2, 2, 2) is None and oversubscription_warning(100000, 1, 2) is None
    assert oversubscription_warning(100000, 808, 2) == (
        "--workers 100000: 808 processes on 2 cores share them (no faster than 2, and each holds a scene's arrays in "
        "memory); leave --workers out for one per core")
    assert "on 1 core share" in oversubscription_warning(3, 3, 1)
