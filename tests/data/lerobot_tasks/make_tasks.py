"""Writes the two tasks tables of tests/sefa_data_tests/test_lerobot_reader_faults.py with pandas itself (the
project does not depend on pandas, so the files are kept here). Rerun with pandas 2 (LeRobot
0.6.1 pins pandas < 3) and pyarrow installed:

    python tests/data/lerobot_tasks/make_tasks.py

tasks_unnamed_index.parquet: a DataFrame indexed by the task strings, index unnamed (pyarrow
shows a column `__index_level_0__`), as 4 of 6 foreign LeRobot v3.0 datasets were found
written. tasks_named_index.parquet: the same with the index named `task`, no `task` column.
"""
from pathlib import Path

import pandas as pd

here = Path(__file__).resolve().parent
tasks = ["Push the T-shaped block onto the target.", "Pick up the red cube."]  # task 0: the Push-T fixture's
df = pd.DataFrame({"task_index": [0, 1]}, index=tasks)
df.to_parquet(here / "tasks_unnamed_index.parquet")
df.rename_axis("task").to_parquet(here / "tasks_named_index.parquet")
