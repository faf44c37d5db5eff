# RabbitMQ from Debian's packages with the official image's RABBITMQ_DEFAULT_USER / _PASS: the local stand-in
# for rabbitmq:3.13. The node name is fixed so that its data directory survives a new container.
ARG BASE
FROM ${BASE}
RUN apt-get update && apt-get install -y --no-install-recommends rabbitmq-server \
    && rm -rf /var/lib/apt/lists/* \
    && install -d -o rabbitmq -g rabbitmq /var/lib/rabbitmq /etc/rabbitmq \
    && chown rabbitmq:rabbitmq /etc/rabbitmq
COPY docker/local/rabbitmq-entrypoint.sh /usr/local/bin/
ENV RABBITMQ_NODENAME=rabbit@localhost HOME=/var/lib/rabbitmq
USER rabbitmq
EXPOSE 5672
ENTRYPOINT ["rabbitmq-entrypoint.sh"]
