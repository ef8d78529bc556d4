"""The streaming client's engine, free of GL and windows: which tiles and bands a view wants (selection.py), getting
their bytes (sources.py, fetch.py, cache.py) and keeping the GPU pool filled with them (engine.py)."""
