"""Learned and exact simulators behind one interface."""
