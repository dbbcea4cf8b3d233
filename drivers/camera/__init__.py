"""Cameras: the Marlin F-080 through libdc1394 (ctypes) and any OpenCV source, chosen from config.
"""
