"""Many flights at once: each replayed, smoothed, mapped and scored as a task of a Dask cluster."""
