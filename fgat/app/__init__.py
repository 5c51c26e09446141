"""Everything that runs things: the command line, the Lightning experiments (modules,
datamodules, callbacks), pipelines, sweeps and their trials, the tracking server, run
fingerprints and report writers."""
