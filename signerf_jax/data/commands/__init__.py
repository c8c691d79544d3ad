"""The data layer's `signerf` subcommands: synthesize (a synthetic scene with ground truth) and
process (a capture's camera poses, recovered with COLMAP): one module each."""
