/*
 * Subscribe to the cellbridge daemon and print each message as one JSON line:
 *   {"topic":"contact","payload":{...}}
 *
 * Needs libzmq and msgpack-c (Debian: libzmq3-dev libmsgpack-dev). Build: make
 * Run:   ./subscriber [-e ENDPOINT] [-n COUNT] [-s SERVER.key -k CLIENT.key_secret] [TOPIC...]
 *
 * -s/-k make it a CURVE client of a daemon bound beyond loopback: the daemon's
 * public key file and this client's secret key file, both written by
 * `cellbridge keys gen` (the client's NAME.key must be in the daemon's
 * allowed_clients_dir).
 *
 * When nothing comes in the first 5 s, not even the daemon's health (published every
 * second), a line on stderr says so and it waits on. Ctrl-C ends it, exit 0.
 */
#define _POSIX_C_SOURCE 200809L /* sigaction, getopt */
#include <msgpack.h>
#include <zmq.h>

#include <errno.h>
#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static void print_json(const msgpack_object *o);

#define QUIET_MS 5000 /* ms without a message before it says so (and waits on) */

static volatile sig_atomic_t stopped; /* Ctrl-C: the end, not an error */

static void on_sigint(int sig)
{
    (void)sig;
    stopped = 1;
}

static void print_string(const char *s, size_t n)
{
    putchar('"');
    for (size_t i = 0; i < n; i++) {
        unsigned char c = (unsigned char)s[i];
        if (c == '"' || c == '\\')
            printf("\\%c", c);
        else if (c < 0x20)
            printf("\\u%04x", c);
        else
            putchar(c);
    }
    putchar('"');
}

static void print_json(const msgpack_object *o)
{
    switch (o->type) {
    case MSGPACK_OBJECT_NIL: printf("null"); break;
    case MSGPACK_OBJECT_BOOLEAN: printf(o->via.boolean ? "true" : "false"); break;
    case MSGPACK_OBJECT_POSITIVE_INTEGER: printf("%llu", (unsigned long long)o->via.u64); break;
    case MSGPACK_OBJECT_NEGATIVE_INTEGER: printf("%lld", (long long)o->via.i64); break;
    case MSGPACK_OBJECT_FLOAT32:
    case MSGPACK_OBJECT_FLOAT64:
        if (isfinite(o->via.f64)) printf("%.17g", o->via.f64); else printf("null");
        break;
    case MSGPACK_OBJECT_STR: print_string(o->via.str.ptr, o->via.str.size); break;
    case MSGPACK_OBJECT_BIN: /* bytes as hex, as `cellbridge sub` prints them */
        putchar('"');
        for (uint32_t i = 0; i < o->via.bin.size; i++) printf("%02x", (unsigned char)o->via.bin.ptr[i]);
        putchar('"');
        break;
    case MSGPACK_OBJECT_ARRAY:
        putchar('[');
        for (uint32_t i = 0; i < o->via.array.size; i++) {
            if (i) putchar(',');
            print_json(&o->via.array.ptr[i]);
        }
        putchar(']');
        break;
    case MSGPACK_OBJECT_MAP:
        putchar('{');
        for (uint32_t i = 0; i < o->via.map.size; i++) {
            const msgpack_object_kv *kv = &o->via.map.ptr[i];
            if (i) putchar(',');
            if (kv->key.type == MSGPACK_OBJECT_STR) print_json(&kv->key);
            else { putchar('"'); msgpack_object_print(stdout, kv->key); putchar('"'); }
            putchar(':');
            print_json(&kv->val);
        }
        putchar('}');
        break;
    default: printf("null"); /* extension types */
    }
}

/* Read the Z85 key after `name = "` in a ZeroMQ certificate file into out[41]. */
static int read_key(const char *path, const char *name, char out[41])
{
    FILE *f = fopen(path, "r");
    char line[256];
    int found = 0;
    if (!f) { perror(path); return -1; }
    while (!found && fgets(line, sizeof line, f)) {
        char *p = strstr(line, name), *q;
        if (p && (q = strchr(p, '"')) && strlen(q + 1) >= 41 && q[41] == '"') {
            memcpy(out, q + 1, 40);
            out[40] = '\0';
            found = 1;
        }
    }
    fclose(f);
    if (!found) fprintf(stderr, "%s: no %s in this file\n", path, name);
    return found ? 0 : -1;
}

static int make_curve_client(void *sock, const char *server_file, const char *client_file)
{
    char server_pub[41], client_pub[41], client_sec[41];
    if (read_key(server_file, "public-key", server_pub) || read_key(client_file, "public-key", client_pub)
        || read_key(client_file, "secret-key", client_sec))
        return -1;
    zmq_setsockopt(sock, ZMQ_CURVE_SERVERKEY, server_pub, 40);
    zmq_setsockopt(sock, ZMQ_CURVE_PUBLICKEY, client_pub, 40);
    zmq_setsockopt(sock, ZMQ_CURVE_SECRETKEY, client_sec, 40);
    return 0;
}

int main(int argc, char **argv)
{
    const char *endpoint = "tcp://127.0.0.1:5560", *server_key = NULL, *client_key = NULL;
    long count = 0, received = 0;
    int opt, rc = 0;
    while ((opt = getopt(argc, argv, "e:n:s:k:")) != -1) {
        switch (opt) {
        case 'e': endpoint = optarg; break;
        case 'n': count = atol(optarg); break;
        case 's': server_key = optarg; break;
        case 'k': client_key = optarg; break;
        default:
            fprintf(stderr, "usage: %s [-e ENDPOINT] [-n COUNT] [-s SERVER.key -k CLIENT.key_secret] [TOPIC...]\n", argv[0]);
            return 2;
        }
    }
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_sigint; /* no SA_RESTART: a wait in libzmq returns EINTR */
    sigaction(SIGINT, &sa, NULL);
    void *ctx = zmq_ctx_new();
    void *sub = zmq_socket(ctx, ZMQ_SUB);
    void *probe = zmq_socket(ctx, ZMQ_SUB); /* the daemon's health alone: is a daemon there? */
    int linger = 0;
    zmq_setsockopt(sub, ZMQ_LINGER, &linger, sizeof linger);
    zmq_setsockopt(probe, ZMQ_LINGER, &linger, sizeof linger);
    if ((server_key || client_key)
        && !(server_key && client_key && make_curve_client(sub, server_key, client_key) == 0
             && make_curve_client(probe, server_key, client_key) == 0)) {
        fprintf(stderr, "CURVE needs both -s SERVER.key and -k CLIENT.key_secret, readable\n");
        rc = 2;
        goto out;
    }
    if (optind == argc)
        zmq_setsockopt(sub, ZMQ_SUBSCRIBE, "", 0); /* every topic */
    for (int i = optind; i < argc; i++)
        zmq_setsockopt(sub, ZMQ_SUBSCRIBE, argv[i], strlen(argv[i])); /* prefix match */
    zmq_setsockopt(probe, ZMQ_SUBSCRIBE, "health", 6);
    if (zmq_connect(sub, endpoint) != 0 || zmq_connect(probe, endpoint) != 0) {
        fprintf(stderr, "%s: %s\n", endpoint, zmq_strerror(zmq_errno()));
        rc = 2;
        goto out;
    }
    /* Connecting never fails: a daemon that is not there says nothing. A running one
     * publishes its health every second, even while the topics asked for are quiet. */
    zmq_pollitem_t first[] = {{sub, 0, ZMQ_POLLIN, 0}, {probe, 0, ZMQ_POLLIN, 0}};
    int ready = zmq_poll(first, 2, QUIET_MS);
    if (ready == 0 || (ready > 0 && !(first[0].revents | first[1].revents)))
        fprintf(stderr, "subscriber: nothing from %s in %d s, not even its health: is the daemon running%s (waiting on; "
                "Ctrl-C stops)\n", endpoint, QUIET_MS / 1000,
                server_key ? " and does it allow this client's key?" : "?");
    zmq_close(probe);
    probe = NULL;
    msgpack_unpacked payload;
    msgpack_unpacked_init(&payload);
    while (!stopped && (count == 0 || received < count)) {
        zmq_msg_t topic, body;
        int more = 0;
        size_t more_size = sizeof more;
        zmq_msg_init(&topic);
        zmq_msg_init(&body);
        if (zmq_msg_recv(&topic, sub, 0) < 0) { /* Ctrl-C (EINTR): the end; anything else an error */
            if (!(stopped || zmq_errno() == EINTR)) rc = 1;
            zmq_msg_close(&topic);
            zmq_msg_close(&body);
            break;
        }
        zmq_getsockopt(sub, ZMQ_RCVMORE, &more, &more_size);
        if (more) zmq_msg_recv(&body, sub, 0);
        int extra = 0;
        while (zmq_getsockopt(sub, ZMQ_RCVMORE, &more, &more_size) == 0 && more) { /* drain a longer message */
            zmq_msg_t part;
            zmq_msg_init(&part);
            zmq_msg_recv(&part, sub, 0);
            zmq_msg_close(&part);
            extra = 1;
        }
        received++;
        printf("{\"topic\":");
        print_string(zmq_msg_data(&topic), zmq_msg_size(&topic));
        if (extra) {
            printf(",\"error\":\"expected 2 frames [topic, payload]\"");
        } else if (msgpack_unpack_next(&payload, zmq_msg_data(&body), zmq_msg_size(&body), NULL) == MSGPACK_UNPACK_SUCCESS) {
            printf(",\"payload\":");
            print_json(&payload.data);
        } else {
            printf(",\"error\":\"payload is not msgpack\"");
        }
        printf("}\n");
        fflush(stdout);
        zmq_msg_close(&topic);
        zmq_msg_close(&body);
    }
    msgpack_unpacked_destroy(&payload);
out:
    if (probe) zmq_close(probe);
    zmq_close(sub);
    zmq_ctx_term(ctx);
    return rc;
}
