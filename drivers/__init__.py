"""Not code: makes drivers/ importable as dobhil.data.drivers so importlib.resources finds it (see setup.py)."""
