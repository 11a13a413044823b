"""Developer tools beside the product: the Makefile's step runner and a real server process for tests and
benchmarks. Nothing in app/ imports them."""
