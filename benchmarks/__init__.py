"""Speed and memory harness: `python -m benchmarks.<name>` writes reports/benchmarks/*.json."""
