"""The IMU side: deltas over a filter step, the time update (thesis eq. 4.1) with its process
noise, the first state (still or moving, its velocity from the GPS), stillness (zero-velocity)
updates, and while the heading is still unknown, levelling against gravity and the bank of
heading hypotheses that places it; the window fit of attitude and biases the GPS calibrations use.
"""
