"""Suite-wide settings.

Hypothesis's per-example deadline is a timed assertion: on a shared two-core machine (CI,
a laptop running the emulator) a slow example says nothing about the code, so the
deadline is off everywhere; speed is measured by the scripts in bench/.
"""

from hypothesis import settings

settings.register_profile("cellbridge", deadline=None)
settings.load_profile("cellbridge")
