"""Force loop tests: emulated runs, safety stops, third-party client, cross-process, CLI."""
