"""esmm.cli: the ``esmm`` command line (see :func:`esmm.cli.main.main`)."""
