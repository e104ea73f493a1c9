"""Continuum-bronchoscope robot model: closed-form kinematics of the ROOM scope (pure numpy)."""
