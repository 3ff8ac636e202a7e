"""Register-level device drivers: blocking, thread-agnostic, no event loop (the actors in
``platformd`` own the threads and the scheduling)."""
