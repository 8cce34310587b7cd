"""The reconstruction tests, grouped as the package is (``model/``, ``solve/``,
``evaluate/``, the job at the top).

Loading this file puts ``tests/reconstruction`` on ``sys.path`` (pytest's ``prepend``
import mode), so the tests in the sub-folders import the shared builders of
``_problems.py`` whichever folder pytest collects first.
"""
