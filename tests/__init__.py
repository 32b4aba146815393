"""nrt's tests, laid out like the package: ``tests/<layer>/`` holds the tests of
``nrt/<layer>/`` (``tests/benchmarks/`` those of ``benchmarks/``), and the tests of nrt's
top-level modules and of the project as a whole sit here. Shared fixtures live in
``tests/conftest.py``; shared code is imported from the ``tests`` package
(``tests.mc_stats``, ``tests.finite_training``, ``tests.conftest``)."""
