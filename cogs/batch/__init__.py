"""`cogs batch`: many sequences through prepare -> train -> eval, on Ray.

    manifest.py   the YAML manifest: read, check whole, entries with defaults merged
    steps.py      what each step does (library calls, no Ray) and when it is done
    runner.py     Ray: one chain of tasks per entry, the live table, the records
    results.py    OUT/results.csv and OUT/results.md
    command.py    the `Batch` sub-command

Ray is an optional dependency (the `batch` extra); nothing here imports it at module level.
"""
