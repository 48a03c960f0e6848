"""mosaicmap's versioned map repository: grid and coordinate conventions, versions, diff, export.

Importing this package is light (numpy only); heavier submodules import their own dependencies.
"""
