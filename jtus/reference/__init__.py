"""Independent PyTorch implementations of DLCTUS, KPN and NSRR, written from the papers'
text rather than from ``jtus/models/``: the references the tests compare jtus against
and ``python -m jtus.bench`` times jtus beside.

Each module imports ``torch`` at its top. jtus never imports this package at runtime;
only the tests and the bench's PyTorch comparison do, and only where ``torch`` is
installed (``pip install -e ".[test]"``). NCHW throughout, as PyTorch's layers are.
"""
