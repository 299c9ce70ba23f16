"""Benchmarks and the command line (`python -m jaxcon demo | bench`). Not part of the library's API: this
package measures the library, against the references in `bench.references`."""
