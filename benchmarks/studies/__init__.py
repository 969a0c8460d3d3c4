"""One-off studies behind the choices of the solvers and the PRN implementation
(``python -m benchmarks.studies.NAME``)."""
