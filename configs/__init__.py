"""Not code: makes configs/ importable as dobhil.data.configs so importlib.resources finds it (see setup.py)."""
