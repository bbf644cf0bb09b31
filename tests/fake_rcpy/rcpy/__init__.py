"""A stand-in for rcpy (librobotcontrol's Python bindings) at the library boundary, for running
``xneck bridge --driver beaglebone`` off the board: put ``tests/fake_rcpy`` on PYTHONPATH.
Encoders stay at 0 counts; motor set values and enable levels are checked like the C library
does, and written to FAKE_RCPY_LOG if set (rcpy._log). In-process tests use the richer FakeBoard of test_bridge_driver.py."""
