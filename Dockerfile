# vtolpose onboard service: `vtolpose run` with the vehicle's configuration mounted at /etc/vtolpose.
#
#   docker build -t vtolpose .
#   docker run -d --name vtolpose --restart unless-stopped --init --network host \
#     --device /dev/ttyUSB0 --device /dev/ttyUSB1 --device /dev/fw1 \
#     --group-add "$(stat -c %g /dev/ttyUSB0)" --group-add "$(stat -c %g /dev/fw1)" \
#     --cap-add SYS_NICE --ulimit rtprio=99 \
#     -v /etc/vtolpose:/etc/vtolpose:ro -v /var/lib/vtolpose:/data \
#     vtolpose
#
# Host networking carries MAVLink (UDP) and Zenoh (TCP/UDP, multicast scouting) as on the host.
# The vehicle file (/etc/vtolpose/vtolpose.yaml) sets sensors.*, outputs.*, run.calibration_file
# (e.g. /etc/vtolpose/calibration.yaml) and, if wanted, run.trajectory under /data and
# run.realtime_priority (what SYS_NICE and rtprio are for; drop both lines without it). A camera
# through V4L2 is --device /dev/video0 instead of /dev/fw1. `docker stop` sends SIGTERM: the
# daemon flushes the fusion buffer and the trajectory, closes its links and exits 0.
FROM python:3.11-slim-bookworm

# libdc1394 for the IIDC (FireWire) camera, which the driver binds with ctypes; glib for OpenCV.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libdc1394-25 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /opt/vtolpose
COPY pyproject.toml README.md __init__.py __main__.py client.py ./
COPY config ./config
COPY estimator ./estimator
COPY drivers ./drivers
COPY service ./service
RUN pip install --no-cache-dir . && rm -rf /opt/vtolpose/build
# The estimator's compiled kernels (numba), compiled here into a cache the service's user owns (numba
# uses a cache only where it may write): the service does not compile at its start.
ENV NUMBA_CACHE_DIR=/var/cache/vtolpose-numba
RUN vtolpose warmup

# Not root: serial ports (dialout) and cameras (video); on hosts whose device groups have other
# ids, pass them with --group-add as above.
RUN useradd --system --create-home --groups dialout,video vtolpose \
    && mkdir -p /data && chown vtolpose /data && chown -R vtolpose "$NUMBA_CACHE_DIR"
USER vtolpose
WORKDIR /data
ENV PYTHONUNBUFFERED=1

ENTRYPOINT ["vtolpose", "run"]
CMD ["--config", "/etc/vtolpose/vtolpose.yaml"]
