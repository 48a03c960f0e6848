"""mosaicmap's batch pipeline: the algorithm modules (flat here), the build and its stages
(:mod:`pipeline.stages`), the command line (:mod:`pipeline.cli`), the importers
(:mod:`pipeline.importers`), the simulators (:mod:`pipeline.simulate`) and test fixtures
(:mod:`pipeline.testing`)."""

__version__ = "0.1.0"
