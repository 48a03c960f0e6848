"""The default configuration files (``*.toml``), installed with mosaicmap as this package
(see ``pipeline.config``); every knob is documented in them."""
