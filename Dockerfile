# Build the release binary, then serve it from a small image as a non-root user.
FROM rust:1-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY api ./api
RUN cargo build --release --locked

FROM debian:bookworm-slim
RUN apt-get update && apt-get install -y --no-install-recommends curl && rm -rf /var/lib/apt/lists/* \
    && useradd --system --uid 10001 --create-home radiosity \
    && mkdir /data && chown radiosity /data
COPY --from=build /src/target/release/radiosity /usr/local/bin/radiosity
COPY scenes/*.gltf /opt/radiosity/scenes/
USER radiosity
VOLUME /data
EXPOSE 8080
HEALTHCHECK --interval=30s --timeout=3s CMD curl -fsS http://127.0.0.1:8080/healthz || exit 1
ENTRYPOINT ["radiosity"]
CMD ["serve", "--addr", "0.0.0.0:8080", "--data-dir", "/data"]
