"""Speed, memory and robustness figures, each against a baseline measured in the same run.

Run each script as a module from the repository's root, so that it shares the tests'
support package (``tests.support``) without touching ``sys.path``::

    python -m bench.bench_worker --repeats 3
"""
