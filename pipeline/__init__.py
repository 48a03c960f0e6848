"""mosaicmap's batch pipeline: simulate, ingest, (register, optimize, render, publish), and the CLI."""

__version__ = "0.1.0"
