"""The mi_tetvr test suite (a package, so that its helpers import as
``tests.helpers`` and ``tests.reference``)."""
