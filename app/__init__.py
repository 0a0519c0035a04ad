"""omniformation app: everything that touches time, threads, files, ports and the browser."""
