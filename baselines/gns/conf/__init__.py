"""Hydra config groups of the GNS plugin (entry point lagfluid.configs): model/, train/, experiment/."""
