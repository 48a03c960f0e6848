"""Fixtures for tests and benchmarks (as ``zarr.testing`` ships its helpers): synthetic maps
(:mod:`.synthmap`) and pose graphs (:mod:`.synthgraph`). Nothing in the pipeline imports them;
the simulators a user runs (``mosaicmap simulate``) are ``pipeline/simulate/``."""
