"""Layer 1: errors, the point-cloud type, threads, platform calls and atomic outputs; imports no other c1mesh layer."""
