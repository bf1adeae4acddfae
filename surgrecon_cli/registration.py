"""The registration library's public entry point (spec section 5): `register` and friends.

A thin alias of `surgrecon_cli.core.registration`, importable without the CLI.
"""

from .core.registration import RegistrationResult, apply_transforms, register, register_pair

__all__ = ["RegistrationResult", "apply_transforms", "register", "register_pair"]
