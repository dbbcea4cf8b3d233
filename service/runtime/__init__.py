"""The onboard runtime: sources → fusion → outputs on one asyncio loop, the daemon that builds it
from configuration, live and replay sources, and the status and health it reports.
"""
