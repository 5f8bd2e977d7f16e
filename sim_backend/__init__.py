"""The simulated IRMA4U prototype: physics (``physics``), hidden effects and faults (``config``), emulated
devices on the real wire protocols, and the lockstep backend that runs them (``backend.SimBackend``)."""
