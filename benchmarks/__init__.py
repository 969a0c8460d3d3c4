"""Benchmark harness: one module per paper table (``python -m benchmarks.<table>``)."""
