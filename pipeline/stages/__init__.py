"""The build and its stages (ingest, register, optimize, orp, render, publish) over a work
directory (:mod:`pipeline.stages.workspace`); the computations they call live flat in
``pipeline/`` and import nothing from here."""
