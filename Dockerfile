# Build the release binary, then run it in a small image as a non-root user.
FROM rust:1-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src ./src
COPY api ./api
RUN cargo build --release --locked

FROM debian:bookworm-slim
RUN useradd --system --uid 10001 --create-home radiosity
COPY --from=build /src/target/release/radiosity /usr/local/bin/radiosity
COPY scenes /opt/radiosity/scenes
USER radiosity
WORKDIR /home/radiosity
# The service (`serve`) arrives with issue 5; until then the image runs the scene summary.
ENTRYPOINT ["radiosity"]
CMD ["scene", "/opt/radiosity/scenes/cornell_moving.gltf"]
