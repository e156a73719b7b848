"""Applications built on the library: ``torchcontact train`` and ``torchcontact export``.

Installed from the repository's top-level ``training/`` and ``export/`` folders (which also run as
``python -m training`` / ``python -m export`` from the repository root): ``pip install`` maps them
to :mod:`torchcontact.apps.training` and :mod:`torchcontact.apps.export`.
"""
