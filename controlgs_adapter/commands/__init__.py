"""Sub-commands of the ``controlgs`` CLI."""
