# Mosquitto 2 from Debian's packages, laid out as eclipse-mosquitto:2 (/mosquitto/config, /mosquitto/data).
ARG BASE
FROM ${BASE}
RUN apt-get update && apt-get install -y --no-install-recommends mosquitto mosquitto-clients \
    && rm -rf /var/lib/apt/lists/* \
    && install -d -o mosquitto -g mosquitto /mosquitto/config /mosquitto/data /mosquitto/log
USER mosquitto
EXPOSE 1883
ENTRYPOINT ["mosquitto", "-c", "/mosquitto/config/mosquitto.conf"]
