"""Speed measurements of the updates and of the whole loop (docs/benchmarks.md); run each as a script."""
