#!/usr/bin/env bash
# A real S3-compatible server for mosaicmap's S3 tests and for trying `s3://` maps locally:
# versitygw (Apache-2.0, Go) serving a directory of this machine, on loopback.
#
#   scripts/s3_server.sh install     build the pinned versitygw into the cache once (go install;
#                                    ~2.5 min of CPU), print the binary's path
#   scripts/s3_server.sh path        print the binary's path; exit 1 when not installed
#   scripts/s3_server.sh start       start a server on 127.0.0.1:$S3_PORT over a new temporary data
#                                    directory, create bucket $S3_BUCKET, print the environment to
#                                    export (eval "$(scripts/s3_server.sh start)")
#   scripts/s3_server.sh stop        stop the server `start` started
#
# Why versitygw: it keeps objects as plain files, starts in milliseconds, and honours S3's
# conditional writes (If-None-Match: * and If-Match: ETag on PUT), which icechunk's commits and
# tags rely on to refuse a second writer.
#
# Environment (all optional):
#   MOSAICMAP_S3_CACHE  where the binary is kept (default ~/.cache/mosaicmap/s3)
#   S3_PORT             listen port for `start` (default 9070)
#   S3_BUCKET           bucket `start` creates (default mosaicmap)
#   S3_ACCESS_KEY / S3_SECRET_KEY   the server's root credentials (default mosaicmap / mosaicmap-secret)
set -euo pipefail

VERSITYGW_VERSION=v1.8.0
CACHE=${MOSAICMAP_S3_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/mosaicmap/s3}
BIN=$CACHE/versitygw-$VERSITYGW_VERSION/versitygw
PORT=${S3_PORT:-9070}
BUCKET=${S3_BUCKET:-mosaicmap}
ACCESS=${S3_ACCESS_KEY:-mosaicmap}
SECRET=${S3_SECRET_KEY:-mosaicmap-secret}
STATE=$CACHE/run-$PORT
# SHA-256 of an empty body: the signed payload hash of a bodiless request.
EMPTY_SHA256=e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855

die() { echo "s3_server.sh: $*" >&2; exit 1; }

install() {
    if [[ -x $BIN ]]; then
        echo "$BIN"
        return
    fi
    command -v go > /dev/null || die "go is not installed (needed to build versitygw $VERSITYGW_VERSION)"
    mkdir -p "$(dirname "$BIN")"
    local t0=$SECONDS
    # nice: the build shares the machine's cores with whatever else runs.
    GOBIN=$(dirname "$BIN") GOFLAGS=-buildvcs=false nice -n 19 \
        go install "github.com/versity/versitygw/cmd/versitygw@$VERSITYGW_VERSION" >&2
    echo "s3_server.sh: versitygw $VERSITYGW_VERSION built in $((SECONDS - t0)) s" >&2
    echo "$BIN"
}

path() {
    [[ -x $BIN ]] || die "versitygw $VERSITYGW_VERSION not installed (run: $0 install)"
    echo "$BIN"
}

# s3 METHOD PATH: one signed request to the server; prints the HTTP status.
s3() {
    curl -s -o /dev/null -w "%{http_code}" --aws-sigv4 "aws:amz:us-east-1:s3" --user "$ACCESS:$SECRET" \
        -H "x-amz-content-sha256: $EMPTY_SHA256" -X "$1" "http://127.0.0.1:$PORT$2" || true
}

start() {
    path > /dev/null
    [[ -f $STATE/pid ]] && kill -0 "$(cat "$STATE/pid")" 2> /dev/null && die "a server runs already on port $PORT (pid $(cat "$STATE/pid"))"
    rm -rf "$STATE"
    mkdir -p "$STATE"
    local data
    data=$(mktemp -d "${TMPDIR:-/tmp}/mosaicmap-s3-data.XXXXXX")
    echo "$data" > "$STATE/data"
    ROOT_ACCESS_KEY_ID=$ACCESS ROOT_SECRET_ACCESS_KEY=$SECRET \
        nohup "$BIN" --port "127.0.0.1:$PORT" --quiet posix "$data" > "$STATE/server.log" 2>&1 &
    echo $! > "$STATE/pid"
    local i
    for i in $(seq 100); do
        [[ $(s3 GET /) == 200 ]] && break
        kill -0 "$(cat "$STATE/pid")" 2> /dev/null || die "the server died: $(tail -3 "$STATE/server.log")"
        sleep 0.1
    done
    [[ $(s3 GET /) == 200 ]] || die "the server did not answer on 127.0.0.1:$PORT within 10 s"
    local code
    code=$(s3 PUT "/$BUCKET")
    [[ $code == 200 ]] || die "creating bucket $BUCKET answered HTTP $code"
    cat << EOF
export AWS_ENDPOINT_URL=http://127.0.0.1:$PORT
export AWS_ACCESS_KEY_ID=$ACCESS
export AWS_SECRET_ACCESS_KEY=$SECRET
export AWS_REGION=us-east-1
# maps go to s3://$BUCKET/PREFIX; stop with: $0 stop
EOF
}

stop() {
    [[ -f $STATE/pid ]] || die "no server started on port $PORT"
    kill "$(cat "$STATE/pid")" 2> /dev/null || true
    [[ -f $STATE/data ]] && rm -rf "$(cat "$STATE/data")"
    rm -rf "$STATE"
}

case "${1:-}" in
    install) install ;;
    path) path ;;
    start) start ;;
    stop) stop ;;
    *) die "usage: $0 install|path|start|stop" ;;
esac
