"""The GPS position update (thesis eq. 4.6): antenna lever arm, per-fix noise and the χ² gate.
"""
