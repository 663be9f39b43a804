"""``python -m hartrao_jax.cli``: the same as the ``hartrao-jax`` command."""

from . import run

if __name__ == "__main__":  # pragma: no cover
    run()
