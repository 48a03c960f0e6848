"""Importers: other recordings turned into drive logs (a ROS 2 bag: :mod:`.bag`; a tiled
scan: :mod:`.tiles`; geotagged photos: :mod:`.geotagged`). The commands over them live in
``pipeline/cli/`` (``import-bag``, ``import-tiles``, ``import-geotagged``)."""
