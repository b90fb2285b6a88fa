"""Performance benchmarks and the soak test of the daemon (`make bench`, `make soak`)."""
