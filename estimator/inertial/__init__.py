"""The IMU side: deltas over a filter step, the time update (thesis eq. 4.1) with its process
noise, the first state from a still start or an in-motion alignment, stillness (zero-velocity)
updates and levelling against gravity while the heading is still unknown.
"""
