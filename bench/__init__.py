"""Benchmarks that measure the service against the paper's protocol and its own targets.

Each module is a harness that returns report tables (bench.report),
so the CLI can print them and write the same numbers to docs/benchmarks/.
"""
