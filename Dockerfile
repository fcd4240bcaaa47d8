# One image for the API and the worker: `loopnet serve` and `loopnet worker` (docker-compose.yml).
FROM python:3.11-slim

WORKDIR /app
# torch first, from the CPU wheel index (the largest layer; it changes least often)
RUN pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
COPY pyproject.toml README.md ./
COPY service service
COPY workers workers
COPY migrations migrations
# editable: the Alembic scripts in migrations/ are read from the source tree
RUN pip install --no-cache-dir -e .

# The data directory (indexes, model versions) is a volume every replica and worker shares;
# pretrained weights are linked from /weights (a mounted copy of ../shared/weights) at start, or
# downloaded on first use where there is network.
# It listens beyond loopback, so API keys are always required (never the open `auto` start):
# create the first key with `docker run ... loopnet keys create --role admin --name me`.
ENV LOOPNET_DATA_DIR=/data \
    TORCH_HOME=/data/torch \
    LOOPNET_HOST=0.0.0.0 \
    LOOPNET_PORT=8000 \
    LOOPNET_AUTH=required
VOLUME /data
EXPOSE 8000
CMD ["loopnet", "serve"]
