"""Hydra config groups of the CConv plugin (entry point lagfluid.configs): model/, train/, experiment/."""
