"""``python -m pipeline.cli``: the ``mosaicmap`` command."""

from pipeline.cli import main

if __name__ == "__main__":
    main()
