"""``python -m dapm_lightning`` runs the ``dapm-lightning`` command line."""

from dapm_lightning.cli import main

if __name__ == "__main__":
    main()
