"""The only package that imports libsumo or sumolib (imported lazily, no work at import time)."""
