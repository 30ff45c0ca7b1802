"""The recipes that train and study the method, installed as ``torchrl_reset_recipes``.

- ``train.py``: the entry point, one training run or a Hydra ``-m`` grid (``python recipes/train.py ...``).
- :mod:`.training`: what a run is built from: its settings and their checks, the agents, the replay buffers,
  the learner, the run folder (checkpoints, tables, the lock, the stop signals) and its records.
- :mod:`.analysis`: reading saved runs: :mod:`.analysis.saved_runs` (a run's config, tables and agents),
  the report (Table 1, Figures 3-5), the stretches, the recoverable check, the screening of many seeds, videos.
- :mod:`.examples`: the whole loop written out on a small chain (``python recipes/examples/demo_chain.py``).
- ``conf/``: the Hydra configuration.
"""
from pathlib import Path

#: the Hydra configuration's folder
CONF = Path(__file__).resolve().parent / "conf"
#: the training entry point (``python recipes/train.py``), which the grids and the screening launch
TRAIN_SCRIPT = Path(__file__).resolve().parent / "train.py"
