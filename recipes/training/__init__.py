"""What a training run is built from (``recipes/train.py`` composes it)."""
