"""The vehicle-side consumer of exported map bundles.

Imports nothing from ``pipeline``: numpy, OpenCV and zarr only, so that it stays light.
"""
