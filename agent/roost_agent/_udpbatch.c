/* Batch reception for the agent's UDP links: recvmmsg with kernel arrival stamps.
 *
 * Why: with a hub client connected the link reader wakes for every datagram, and read in
 * Python each wake-up cost a recvmsg per datagram (its ancillary data parsed into a list
 * of tuples and a struct), then one more recvmsg that fails with EAGAIN and raises
 * BlockingIOError (an exception object and its message built, then caught). Here one
 * system call takes every queued datagram (up to BATCH at a time) and an empty queue is
 * an empty list. roost_agent.transport falls back to the Python reads where this module
 * is not built (no C compiler at install); both give the same (data, sender, stamp)
 * triples.
 *
 * receive(fd, limit) -> list of (bytes, (host, port) | None, float | None): up to
 * ``limit`` datagrams in arrival order; the stamp is the kernel's CLOCK_REALTIME arrival
 * time (SO_TIMESTAMPNS) in seconds, None when the socket does not ask for it. Empty
 * datagrams carry nothing and are skipped. OSError for a failure other than an empty
 * queue or a refused earlier send (ECONNREFUSED, which the Python reads also ignore).
 *
 * send(fd, data, (host, port)): one datagram, sent without letting go of the GIL
 * (roost_agent.transport.send_to; why at send_datagram below).
 *
 * The hub's fast path (roost_agent.fastpath), in the same module as its reads are these:
 * the active autopilot's frames routed to plain UDP clients in C. Why: with a hub client connected the link reader woke for every datagram so routed
 * frames were not held back, and each wake-up (poll, read, parse, the source lock and
 * health bookkeeping, the send) cost the agent more in Python than a C router spends on
 * a whole message. Here the reader waits in C, and each datagram of the active autopilot
 * is read (recvmmsg, kernel arrival stamps), checked and sent on to the clients (sendmmsg:
 * one per client for the frames of every datagram one read took) in C at once, without
 * the GIL: it is taken again only to make what Python is to see (a run of them is made
 * once, when it closes), so the interpreter's lock is not passed back and forth at every
 * wake-up (about a tenth of the reader's time); Python gets what was read in one batch,
 * when the decision loop is due, when something must be seen at once, or when the batch is full,
 * and judges it exactly as before (source lock, health, the hub's own bookkeeping).
 *
 * What is forwarded here is exactly what the Python path would forward to a plain
 * client, or nothing (then Python forwards it, and this call forwards nothing more, so
 * clients see frames in arrival order): a datagram from the locked address that holds
 * only whole MAVLink 2 frames, unsigned, of known message ids with a good CRC, from the
 * autopilot's system and component, none addressed to the agent (its component and the
 * autopilot's system) and no log reply while the agent holds the log session. The hub
 * hands a route here only when no rewrite, signature or TCP client is involved
 * (roost_agent.hub.Hub.fast_route).
 *
 * set_messages(table): {msg_id: (crc_extra, target_system offset, target_component
 * offset, time_boot_ms offset)} (offset -1: the message has no such field), the known
 * message ids.
 *
 * pump(bulk_fd, urgent_fd, wake_fds, (timeout_s, due_s, age_s, offset, boot_due_s,
 *      boot_age_s), clients, locked, sysid, compid, agent_comp, log_busy, urgent_returns,
 *      held, limit, routine, runs)
 *   -> (items, held, woke): waits up to timeout_s, and up to due_s unless the autopilot's
 *   frames keep coming: with age_s >= 0, each datagram routed postpones that deadline to
 *   its arrival (kernel stamp minus offset: the agent's monotonic clock) plus age_s (the
 *   health tracker's thresholds on the last message's age: a silence is seen when it
 *   falls due, and a stream that flows wakes nobody); likewise, while runs are taken and
 *   with boot_age_s >= 0, up to boot_due_s unless frames whose time_boot_ms advances keep
 *   coming (frozen telemetry), each postponing it to its arrival plus boot_age_s. items are (data, sender, stamp, routed,
 *   frames) in arrival order (routed: sent to every client here; frames: for a routed
 *   datagram of routine frames only, their summary (id, sequence number, time_boot_ms or
 *   -1, ...), else None: ``routine`` is a bitmap of the message ids Python reads no further
 *   than that, roost_agent.fastpath.routine_bitmap; why: parsing them and running them
 *   through the link, the hub and the tracker was most of Python's time per message);
 *   with ``runs`` (None: none), datagrams of the stream's bulk come as runs instead (see
 *   "Runs" below);
 *   held: read but possibly
 *   newer than something still queued on the other socket of a steered pair (the
 *   Python reader's rule, roost_agent.transport._Udp.receive_batch), to be passed back;
 *   woke: whether a wake fd became readable.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <arpa/inet.h>
#include <errno.h>
#include <math.h>
#include <netinet/in.h>
#include <poll.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>

#define BATCH 16
#define SLOT 65536
#define CONTROL 64
#define MAX_FRAMES 64 /* frames of one datagram forwarded here; more: Python's */
#define OUTBOX MAX_FRAMES /* frames sent with one sendmmsg per client (Outbox) */
#define V2_MAGIC 0xFD
#define V2_HEADER 10
#define LOG_ENTRY 118
#define LOG_DATA 120

typedef struct {
    unsigned int id;
    unsigned char crc_extra;
    int target_system, target_component, boot_at;
} Known;

static Known *known;
static Py_ssize_t known_count;
static char *slots;

/* A datagram read, or a run of them. Read here, its bytes and sender stay C's (the call's
 * Arena, ``from``) until Python is to see it (made): a datagram routed in a run never
 * becomes a Python object, so the route needs no GIL (pump). */
typedef struct {
    PyObject *data;   /* NULL: not made yet (the arena's ``size`` bytes at ``at``) */
    PyObject *sender; /* NULL: not made yet (``from``, or the locked address) */
    double stamp;     /* NAN: none */
    int urgent;
    PyObject *frames; /* routed, every frame routine: (id, seq, time_boot_ms | -1, ...) */
    PyObject *run;    /* not a datagram: a run of them, taken together (Run) */
    Py_ssize_t at, size;
    struct sockaddr_in from;
    socklen_t from_length;
    int locked; /* sent from the locked address */
} Entry;

/* The bytes of the datagrams one read took, until they are routed or made objects. */
typedef struct {
    unsigned char *bytes;
    Py_ssize_t used, size;
} Arena;

static const Known *lookup(unsigned int id) {
    Py_ssize_t lo = 0, hi = known_count;
    while (lo < hi) {
        Py_ssize_t mid = (lo + hi) / 2;
        if (known[mid].id < id) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    return lo < known_count && known[lo].id == id ? &known[lo] : NULL;
}

static int compare_known(const void *a, const void *b) {
    unsigned int x = ((const Known *)a)->id, y = ((const Known *)b)->id;
    return x < y ? -1 : x > y;
}

static PyObject *set_messages(PyObject *module, PyObject *table) {
    (void)module;
    if (!PyDict_Check(table)) {
        PyErr_SetString(PyExc_TypeError, "set_messages: a dict");
        return NULL;
    }
    Py_ssize_t n = PyDict_Size(table), pos = 0, i = 0;
    Known *out = PyMem_RawMalloc(sizeof(Known) * (size_t)(n ? n : 1));
    if (out == NULL) {
        return PyErr_NoMemory();
    }
    PyObject *key, *value;
    while (PyDict_Next(table, &pos, &key, &value)) {
        unsigned long id = PyLong_AsUnsignedLong(key);
        int crc, ts, tc, boot;
        if ((id == (unsigned long)-1 && PyErr_Occurred()) ||
            !PyArg_ParseTuple(value, "iiii", &crc, &ts, &tc, &boot)) {
            PyMem_RawFree(out);
            return NULL;
        }
        out[i].id = (unsigned int)id;
        out[i].crc_extra = (unsigned char)crc;
        out[i].target_system = ts;
        out[i].target_component = tc;
        out[i].boot_at = boot;
        i++;
    }
    qsort(out, (size_t)n, sizeof(Known), compare_known);
    PyMem_RawFree(known);
    known = out;
    known_count = n;
    Py_RETURN_NONE;
}

/* X.25 (MCRF4XX), as MAVLink's crc_accumulate. */
static unsigned short crc_add(unsigned short crc, unsigned char byte) {
    unsigned char tmp = byte ^ (unsigned char)(crc & 0xFF);
    tmp ^= (unsigned char)(tmp << 4);
    return (unsigned short)((crc >> 8) ^ ((unsigned short)tmp << 8) ^ ((unsigned short)tmp << 3) ^
                            (tmp >> 4));
}

typedef struct {
    int sysid, compid, agent_comp, log_busy;
    const unsigned char *routine; /* bit per message id: Python needs only its summary */
    Py_ssize_t routine_bytes;
} Rules;

static int is_routine(const Rules *rules, unsigned int id) {
    return (Py_ssize_t)(id >> 3) < rules->routine_bytes && (rules->routine[id >> 3] >> (id & 7)) & 1;
}

/* A frame's time_boot_ms (MAVLink 2 drops a payload's trailing zeros), or -1: none. */
static long long boot_time_of(const unsigned char *payload, unsigned int mlen, const Known *k) {
    if (k->boot_at < 0) {
        return -1;
    }
    unsigned long long value = 0;
    for (int i = 3; i >= 0; i--) {
        unsigned int at = (unsigned int)k->boot_at + (unsigned int)i;
        value = value << 8 | (at < mlen ? payload[at] : 0);
    }
    return (long long)value;
}

/* Where the frames of a forwardable datagram start and end (count), or -1, each
 * summarised in ``summary`` (id, sequence number, time_boot_ms or -1); ``*routine``:
 * whether every frame is of a routine message id. */
static int frames_of(const unsigned char *d, Py_ssize_t total, const Rules *rules,
                     Py_ssize_t *starts, Py_ssize_t *ends, int *routine, long long *summary) {
    Py_ssize_t at = 0;
    int count = 0;
    *routine = 1;
    if (total == 0) {
        return -1;
    }
    while (at < total) {
        if (count == MAX_FRAMES || total - at < V2_HEADER + 2 || d[at] != V2_MAGIC) {
            return -1;
        }
        unsigned int mlen = d[at + 1];
        if (d[at + 2] != 0) { /* signed, or flags nobody knows: Python's */
            return -1;
        }
        Py_ssize_t end = at + V2_HEADER + mlen + 2;
        if (end > total) {
            return -1;
        }
        unsigned int id = d[at + 7] | (unsigned int)d[at + 8] << 8 | (unsigned int)d[at + 9] << 16;
        const Known *k = lookup(id);
        if (k == NULL || d[at + 5] != rules->sysid || d[at + 6] != rules->compid) {
            return -1;
        }
        if (rules->log_busy && (id == LOG_ENTRY || id == LOG_DATA)) {
            return -1;
        }
        const unsigned char *payload = d + at + V2_HEADER;
        if (k->target_component >= 0) {
            int tc = (unsigned int)k->target_component < mlen ? payload[k->target_component] : 0;
            int ts = k->target_system < 0                           ? -1
                     : (unsigned int)k->target_system < mlen ? payload[k->target_system]
                                                              : 0;
            if (tc == rules->agent_comp && ts == rules->sysid) {
                return -1; /* an answer to the agent: it stays with the agent */
            }
        }
        unsigned short crc = 0xFFFF;
        for (Py_ssize_t i = at + 1; i < at + V2_HEADER + (Py_ssize_t)mlen; i++) {
            crc = crc_add(crc, d[i]);
        }
        crc = crc_add(crc, k->crc_extra);
        Py_ssize_t crc_at = at + V2_HEADER + mlen;
        if ((crc & 0xFF) != d[crc_at] || (crc >> 8) != d[crc_at + 1]) {
            return -1;
        }
        if (!is_routine(rules, id)) {
            *routine = 0;
        }
        summary[count * 3] = id;
        summary[count * 3 + 1] = d[at + 4];
        summary[count * 3 + 2] = boot_time_of(payload, mlen, k);
        starts[count] = at;
        ends[count] = end;
        count++;
        at = end;
    }
    return count;
}

typedef struct {
    int fd;
    struct sockaddr_in address;
} Client;

/* The frames of one read's datagrams go out together: one sendmmsg per client for all of
 * them instead of one per datagram (a read takes every datagram queued, so under load
 * several share a wake-up, and each system call has a fixed price). The frames stay in
 * arrival order, and leave before the next wait or the return to Python. */
typedef struct {
    struct iovec vectors[OUTBOX];
    int count;
} Outbox;

static void flush(Outbox *box, const Client *clients, int n_clients) {
    struct mmsghdr messages[OUTBOX];
    for (int c = 0; c < n_clients; c++) {
        memset(messages, 0, sizeof(struct mmsghdr) * (size_t)box->count);
        for (int i = 0; i < box->count; i++) {
            messages[i].msg_hdr.msg_iov = &box->vectors[i];
            messages[i].msg_hdr.msg_iovlen = 1;
            messages[i].msg_hdr.msg_name = (void *)&clients[c].address;
            messages[i].msg_hdr.msg_namelen = sizeof(struct sockaddr_in);
        }
        int sent = 0;
        while (sent < box->count) {
            int got = sendmmsg(clients[c].fd, messages + sent, (unsigned int)(box->count - sent),
                               MSG_DONTWAIT);
            /* as the Python path: a frame whose send to a UDP client fails is dropped */
            sent += got > 0 ? got : 1;
        }
    }
    box->count = 0;
}

static void forward(Outbox *box, const unsigned char *d, int count, const Py_ssize_t *starts,
                    const Py_ssize_t *ends, const Client *clients, int n_clients) {
    if (box->count + count > OUTBOX) {
        flush(box, clients, n_clients);
    }
    for (int i = 0; i < count; i++) {
        box->vectors[box->count].iov_base = (void *)(d + starts[i]);
        box->vectors[box->count].iov_len = (size_t)(ends[i] - starts[i]);
        box->count++;
    }
}

static double stamp_of(struct msghdr *header) {
    for (struct cmsghdr *c = CMSG_FIRSTHDR(header); c != NULL; c = CMSG_NXTHDR(header, c)) {
        if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SCM_TIMESTAMPNS &&
            c->cmsg_len >= CMSG_LEN(sizeof(struct timespec))) {
            struct timespec ts;
            memcpy(&ts, CMSG_DATA(c), sizeof ts);
            return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
        }
    }
    return NAN;
}

/* Whether the sender is the locked address (``locked`` NULL: none is). */
static int is_locked(const struct sockaddr_in *a, socklen_t length,
                     const struct sockaddr_in *locked) {
    return locked != NULL && length >= sizeof(struct sockaddr_in) && a->sin_family == AF_INET &&
           a->sin_port == locked->sin_port && a->sin_addr.s_addr == locked->sin_addr.s_addr;
}

/* The sender as a (host, port) tuple (None: not an IPv4 address); with the GIL. */
static PyObject *sender_tuple(const struct sockaddr_in *a, socklen_t length) {
    if (length < sizeof(struct sockaddr_in) || a->sin_family != AF_INET) {
        Py_RETURN_NONE;
    }
    char host[INET_ADDRSTRLEN];
    if (inet_ntop(AF_INET, &a->sin_addr, host, sizeof host) == NULL) {
        Py_RETURN_NONE;
    }
    return Py_BuildValue("(si)", host, (int)ntohs(a->sin_port));
}

typedef struct {
    Entry *items;
    Py_ssize_t count, size;
} Entries;

/* Room for ``needed`` items of ``item`` bytes in ``*buffer`` (``*size`` of them now),
 * doubling from ``first``; the raw allocator, so it needs no GIL. -1: no memory (the
 * caller says so with the GIL). */
static int grow(void **buffer, Py_ssize_t *size, Py_ssize_t needed, size_t item,
                Py_ssize_t first) {
    if (needed <= *size) {
        return 0;
    }
    Py_ssize_t larger = *size ? *size : first;
    while (larger < needed) {
        larger *= 2;
    }
    void *grown = PyMem_RawRealloc(*buffer, item * (size_t)larger);
    if (grown == NULL) {
        return -1;
    }
    *buffer = grown;
    *size = larger;
    return 0;
}

/* Room for ``more`` entries, so that moving entries between lists cannot fail. */
static int reserve(Entries *list, Py_ssize_t more) {
    void *items = list->items;
    if (grow(&items, &list->size, list->count + more, sizeof(Entry), 64) < 0) {
        return -1;
    }
    list->items = items;
    return 0;
}

static int push(Entries *list, Entry entry) {
    if (reserve(list, 1) < 0) {
        return -1;
    }
    list->items[list->count++] = entry;
    return 0;
}

static void clear(Entries *list) {
    for (Py_ssize_t i = 0; i < list->count; i++) {
        Py_XDECREF(list->items[i].data);
        Py_XDECREF(list->items[i].sender);
        Py_XDECREF(list->items[i].frames);
        Py_XDECREF(list->items[i].run);
    }
    PyMem_RawFree(list->items);
    list->items = NULL;
    list->count = list->size = 0;
}

/* The entry's bytes and their length, wherever they are. */
static const unsigned char *bytes_of(const Entry *e, const Arena *arena, Py_ssize_t *size) {
    if (e->data != NULL) {
        *size = PyBytes_GET_SIZE(e->data);
        return (const unsigned char *)PyBytes_AS_STRING(e->data);
    }
    *size = e->size;
    return arena->bytes + e->at;
}

/* The entry's bytes and sender as the objects Python reads (with the GIL); -1: failed. */
static int make(Entry *e, const Arena *arena, PyObject *locked_obj) {
    if (e->run != NULL) {
        return 0; /* a run is made when it closes */
    }
    if (e->data == NULL) {
        e->data = PyBytes_FromStringAndSize((const char *)arena->bytes + e->at, e->size);
        if (e->data == NULL) {
            return -1;
        }
    }
    if (e->sender == NULL) {
        e->sender = e->locked ? Py_NewRef(locked_obj) : sender_tuple(&e->from, e->from_length);
        if (e->sender == NULL) {
            return -1;
        }
    }
    return 0;
}

/* Up to ``limit`` queued datagrams of ``fd`` appended to ``out``, their bytes to ``arena``
 * (``locked``: the address whose datagrams are marked locked, NULL: none). Needs no GIL.
 * -1: a failed read (errno), -2: no memory. */
static int read_socket(int fd, Py_ssize_t limit, int urgent, const struct sockaddr_in *locked,
                       Entries *out, Arena *arena) {
    struct mmsghdr messages[BATCH];
    struct iovec vectors[BATCH];
    struct sockaddr_in addresses[BATCH];
    union {
        char bytes[CONTROL];
        struct cmsghdr align;
    } controls[BATCH];
    int total = 0;
    while (limit > 0) {
        unsigned int want = limit < BATCH ? (unsigned int)limit : BATCH;
        memset(messages, 0, sizeof(struct mmsghdr) * want);
        for (unsigned int i = 0; i < want; i++) {
            vectors[i].iov_base = slots + (size_t)i * SLOT;
            vectors[i].iov_len = SLOT;
            struct msghdr *h = &messages[i].msg_hdr;
            h->msg_iov = &vectors[i];
            h->msg_iovlen = 1;
            h->msg_name = &addresses[i];
            h->msg_namelen = sizeof addresses[i];
            h->msg_control = controls[i].bytes;
            h->msg_controllen = CONTROL;
        }
        int got = recvmmsg(fd, messages, want, MSG_DONTWAIT, NULL);
        if (got < 0) {
            if (errno == EAGAIN || errno == EWOULDBLOCK || errno == ECONNREFUSED) {
                break;
            }
            return -1;
        }
        for (int i = 0; i < got; i++) {
            struct msghdr *h = &messages[i].msg_hdr;
            Py_ssize_t size = (Py_ssize_t)messages[i].msg_len;
            if (size == 0) {
                continue;
            }
            void *bytes = arena->bytes;
            if (grow(&bytes, &arena->size, arena->used + size, 1, 4096) < 0) {
                return -2;
            }
            arena->bytes = bytes;
            memcpy(arena->bytes + arena->used, slots + (size_t)i * SLOT, (size_t)size);
            Entry e = {.data = NULL,
                       .sender = NULL,
                       .stamp = stamp_of(h),
                       .urgent = urgent,
                       .frames = NULL,
                       .run = NULL,
                       .at = arena->used,
                       .size = size,
                       .from = addresses[i],
                       .from_length = h->msg_namelen,
                       .locked = is_locked(&addresses[i], h->msg_namelen, locked)};
            if (push(out, e) < 0) {
                return -2;
            }
            arena->used += size;
            total++;
        }
        limit -= got;
        if ((unsigned int)got < want) {
            break;
        }
    }
    return total;
}

static double realtime(void) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

static double monotonic(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

static double arrival(const Entry *e) { return isnan(e->stamp) ? INFINITY : e->stamp; }

static int compare_entries(const void *a, const void *b) {
    double x = arrival(a), y = arrival(b);
    return x < y ? -1 : x > y;
}

static int address_of(PyObject *pair, struct sockaddr_in *out) {
    const char *host;
    int port;
    if (!PyArg_ParseTuple(pair, "si", &host, &port)) {
        return -1;
    }
    memset(out, 0, sizeof *out);
    out->sin_family = AF_INET;
    out->sin_port = htons((unsigned short)port);
    if (inet_pton(AF_INET, host, &out->sin_addr) != 1) {
        PyErr_Format(PyExc_ValueError, "not an IPv4 address: %s", host);
        return -1;
    }
    return 0;
}

static PyObject *entry_tuple(const Entry *e, int routed) {
    if (e->run != NULL) {
        return Py_NewRef(e->run);
    }
    PyObject *when = isnan(e->stamp) ? Py_NewRef(Py_None) : PyFloat_FromDouble(e->stamp);
    if (when == NULL) {
        return NULL;
    }
    PyObject *out = routed < 0 ? PyTuple_Pack(3, e->data, e->sender, when)
                               : PyTuple_Pack(5, e->data, e->sender, when,
                                              routed ? Py_True : Py_False,
                                              e->frames != NULL ? e->frames : Py_None);
    Py_DECREF(when);
    return out;
}

static int ensure_slots(void) {
    if (slots == NULL) {
        slots = PyMem_RawMalloc((size_t)BATCH * SLOT);
        if (slots == NULL) {
            PyErr_NoMemory();
            return -1;
        }
    }
    return 0;
}

static PyObject *receive(PyObject *module, PyObject *args) {
    (void)module;
    int fd;
    Py_ssize_t limit;
    if (!PyArg_ParseTuple(args, "in:receive", &fd, &limit)) {
        return NULL;
    }
    Entries read = {0};
    Arena arena = {0};
    PyObject *out = NULL;
    if (ensure_slots() < 0) {
        goto done;
    }
    int got = read_socket(fd, limit, 0, NULL, &read, &arena);
    if (got < 0) {
        if (got == -1) {
            PyErr_SetFromErrno(PyExc_OSError);
        } else {
            PyErr_NoMemory();
        }
        goto done;
    }
    out = PyList_New(read.count);
    for (Py_ssize_t i = 0; out != NULL && i < read.count; i++) {
        PyObject *item = make(&read.items[i], &arena, Py_None) < 0
                             ? NULL
                             : entry_tuple(&read.items[i], -1);
        if (item == NULL) {
            Py_CLEAR(out);
            break;
        }
        PyList_SET_ITEM(out, i, item);
    }
done:
    clear(&read);
    PyMem_RawFree(arena.bytes);
    return out;
}

/* One datagram to ``address`` without letting go of the GIL (Python's sendto releases
 * it, and under contention a thread that released it waits a switch interval to get it
 * back: a hub client's command would wait for whatever Python runs elsewhere). A UDP
 * send does not block for long: the kernel queues the datagram or refuses it at once
 * (MSG_DONTWAIT: BlockingIOError, as on a non-blocking socket). */
static PyObject *send_datagram(PyObject *module, PyObject *args) {
    (void)module;
    int fd;
    Py_buffer data;
    PyObject *where;
    if (!PyArg_ParseTuple(args, "iy*O:send", &fd, &data, &where)) {
        return NULL;
    }
    struct sockaddr_in address;
    if (address_of(where, &address) < 0) {
        PyBuffer_Release(&data);
        return NULL;
    }
    ssize_t sent = sendto(fd, data.buf, (size_t)data.len, MSG_DONTWAIT,
                          (const struct sockaddr *)&address, sizeof address);
    PyBuffer_Release(&data);
    if (sent < 0) {
        return PyErr_SetFromErrno(PyExc_OSError);
    }
    Py_RETURN_NONE;
}

/* (id, seq, time_boot_ms | -1, ...) of ``count`` routine frames, for Python. */
static PyObject *summarise(const long long *summary, int count) {
    PyObject *out = PyTuple_New(count * 3);
    for (int i = 0; out != NULL && i < count * 3; i++) {
        PyObject *value = PyLong_FromLongLong(summary[i]);
        if (value == NULL) {
            Py_CLEAR(out);
            break;
        }
        PyTuple_SET_ITEM(out, i, value);
    }
    return out;
}

/* Runs: the bulk of the active autopilot's stream taken by Python as a whole.
 *
 * Why: even summarised, each routed datagram cost Python a tuple, a float and a pass
 * through the link, the hub and the health tracker, and the kinds whose content the
 * tracker reads (ATTITUDE at 100 Hz, GLOBAL_POSITION_INT at 50 Hz) were parsed whole:
 * most of the agent's CPU time per routed message. Of what the tracker reads there, only
 * a change matters (the tilt's class) or the latest value (attitude, position). So
 * consecutive routed datagrams of such kinds become one run: its first and last arrival
 * (the agent's monotonic clock), its worst gap, its frames per message id, its highest
 * time_boot_ms and when that arrived, the last sequence number, and the last frame of
 * each kept kind whole (ATTITUDE, GLOBAL_POSITION_INT) for Python to read.
 *
 * A run ends, so that Python judges exactly what it judged frame by frame: before a
 * datagram it does not take (a kind outside the rules, from another address, not routed
 * here), before a gap of ``gap_limit`` (the tracker's silence threshold: Python sees the
 * silence end), with the datagram that reaches ``window_end`` (the tracker's rate window
 * closes at that message and may learn another silence threshold: runs stop, as they do
 * once a wake-up descriptor woke the call), and when its table of message ids is full. A
 * datagram whose time_boot_ms steps back by ``backstep`` or more (a reboot claim), or
 * which holds a HEARTBEAT (a claim may follow), goes to Python whole and stops runs, as
 * does an ATTITUDE whose tilt class (0: level, 1: past warn_deg, 2: past max_deg)
 * differs from the last one's (Python sees each change; the class it knew comes in as
 * tilt_class, -1: none yet).
 *
 * A datagram of a state kind (SYS_STATUS, EXTENDED_SYS_STATE, ESTIMATOR_STATUS,
 * EKF_STATUS_REPORT: what the tracker reads of them is a state, of which only a change
 * matters) joins a run while the fields the tracker reads hold what it holds (``states``:
 * per kind its id and each field's payload offset, size and the value held, -1: none
 * yet); one that says something else goes whole and stops runs, and one that would close
 * the tracker's rate window goes whole (read whole, Python compares its judgement before
 * and after it, and the window's close may change whether the stream counts as fast).
 *
 * Whatever stops runs also ends the call: Python reads it at once, so no fact waits for
 * the read interval, and the next call takes runs again from the tracker's new state
 * (but an urgent datagram while ``urgent_returns`` is false waits, as it always did:
 * the caller then waits no longer than the steered read interval).
 *
 * rules: (kinds bitmap, (kept ids...), heartbeat id, (attitude id, roll at, pitch at,
 *         warn_deg, max_deg, tilt_class), gap_limit_s, window_end, boot_max,
 *         backstep_ms, ((id, ((offset, size, held), ...)), ...))
 * run tuple: (first_at, last_at, max_gap, frames, datagrams, bytes, last_seq, boot_max,
 *             boot_max_at, (id, count, ...), (frame, at, ...)) */
#define RUN_KINDS 64
#define MAX_KEPT 4
#define FRAME_MAX 280
#define MAX_STATES 4
#define MAX_STATE_FIELDS 2

typedef struct {
    unsigned int id;
    int n_fields;
    int at[MAX_STATE_FIELDS], size[MAX_STATE_FIELDS];
    long long held[MAX_STATE_FIELDS]; /* -1: the tracker holds none yet */
} StateKind;

typedef struct {
    int on;
    const unsigned char *kinds;
    Py_ssize_t kinds_bytes;
    unsigned int kept_ids[MAX_KEPT];
    int n_kept;
    unsigned int heartbeat_id, attitude_id;
    int roll_at, pitch_at, tilt_class;
    double warn_deg, max_deg, gap_limit, window_end;
    long long boot_max, backstep;
    StateKind states[MAX_STATES];
    int n_states;
} RunRules;

typedef struct {
    int open;
    double first_at, last_at, max_gap, boot_max_at;
    long frames, datagrams, bytes;
    int last_seq, n_kinds;
    long long boot_max;
    unsigned int ids[RUN_KINDS];
    long counts[RUN_KINDS];
    unsigned char kept[MAX_KEPT][FRAME_MAX];
    int kept_len[MAX_KEPT];
    double kept_at[MAX_KEPT];
} Run;

/* ((id, ((offset, size, held), ...)), ...) into r->states; -1: a bad table. */
static int parse_states(PyObject *in, RunRules *r) {
    Py_ssize_t n = PySequence_Size(in);
    if (n < 0) {
        return -1;
    }
    if (n > MAX_STATES) {
        PyErr_SetString(PyExc_ValueError, "pump: too many state kinds");
        return -1;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        StateKind *k = &r->states[i];
        PyObject *item = PySequence_GetItem(in, i), *fields;
        int ok = item != NULL && PyArg_ParseTuple(item, "IO", &k->id, &fields);
        Py_XDECREF(item);
        if (!ok) {
            return -1;
        }
        Py_ssize_t m = PySequence_Size(fields);
        if (m < 0) {
            return -1;
        }
        if (m > MAX_STATE_FIELDS) {
            PyErr_SetString(PyExc_ValueError, "pump: too many fields of a state kind");
            return -1;
        }
        for (Py_ssize_t j = 0; j < m; j++) {
            PyObject *field = PySequence_GetItem(fields, j);
            ok = field != NULL &&
                 PyArg_ParseTuple(field, "iiL", &k->at[j], &k->size[j], &k->held[j]);
            Py_XDECREF(field);
            if (!ok) {
                return -1;
            }
            if (k->size[j] != 1 && k->size[j] != 2 && k->size[j] != 4) {
                PyErr_SetString(PyExc_ValueError, "pump: a state field of 1, 2 or 4 bytes");
                return -1;
            }
        }
        k->n_fields = (int)m;
        r->n_states = (int)i + 1;
    }
    return 0;
}

static int parse_run_rules(PyObject *in, RunRules *r) {
    memset(r, 0, sizeof *r);
    if (in == Py_None) {
        return 0;
    }
    PyObject *kept, *tilt, *states;
    Py_ssize_t kinds_bytes;
    const char *kinds;
    if (!PyArg_ParseTuple(in, "y#OIOddLLO", &kinds, &kinds_bytes, &kept, &r->heartbeat_id,
                          &tilt, &r->gap_limit, &r->window_end, &r->boot_max, &r->backstep,
                          &states) ||
        parse_states(states, r) < 0 ||
        !PyArg_ParseTuple(tilt, "Iiiddi", &r->attitude_id, &r->roll_at, &r->pitch_at,
                          &r->warn_deg, &r->max_deg, &r->tilt_class)) {
        return -1;
    }
    r->kinds = (const unsigned char *)kinds;
    r->kinds_bytes = kinds_bytes;
    Py_ssize_t n = PySequence_Size(kept);
    if (n < 0) {
        return -1;
    }
    for (Py_ssize_t i = 0; i < n && r->n_kept < MAX_KEPT; i++) {
        PyObject *item = PySequence_GetItem(kept, i);
        if (item == NULL) {
            return -1;
        }
        r->kept_ids[r->n_kept++] = (unsigned int)PyLong_AsUnsignedLong(item);
        Py_DECREF(item);
        if (PyErr_Occurred()) {
            return -1;
        }
    }
    r->on = 1;
    return 0;
}

static int in_bitmap(const unsigned char *bits, Py_ssize_t size, unsigned int id) {
    return (Py_ssize_t)(id >> 3) < size && (bits[id >> 3] >> (id & 7)) & 1;
}

static float float_at(const unsigned char *payload, unsigned int mlen, int at) {
    unsigned char raw[4];
    for (int i = 0; i < 4; i++) {
        unsigned int where = (unsigned int)at + (unsigned int)i;
        raw[i] = where < mlen ? payload[where] : 0;
    }
    float value;
    memcpy(&value, raw, sizeof value); /* little-endian, as the wire and the hosts */
    return value;
}

/* The tilt class of an ATTITUDE frame: the health tracker's tilt_degrees, compared. */
static int tilt_class_of(const unsigned char *frame, const RunRules *r) {
    unsigned int mlen = frame[1];
    const unsigned char *payload = frame + V2_HEADER;
    double c = cos((double)float_at(payload, mlen, r->roll_at)) *
               cos((double)float_at(payload, mlen, r->pitch_at));
    double tilt = acos(c < -1.0 ? -1.0 : c > 1.0 ? 1.0 : c) * 180.0 / M_PI;
    double warn = r->warn_deg < r->max_deg ? r->warn_deg : r->max_deg;
    return tilt > r->max_deg ? 2 : tilt > warn ? 1 : 0;
}

/* An unsigned little-endian field of ``size`` bytes at ``at`` (MAVLink 2 drops a
 * payload's trailing zeros: bytes past ``mlen`` read as zero). */
static long long field_at(const unsigned char *payload, unsigned int mlen, int at, int size) {
    long long value = 0;
    for (int i = size - 1; i >= 0; i--) {
        unsigned int where = (unsigned int)at + (unsigned int)i;
        value = (value << 8) | (where < mlen ? payload[where] : 0);
    }
    return value;
}

/* Whether a frame of a state kind says what the tracker holds (every field read). */
static int state_holds(const StateKind *k, const unsigned char *frame) {
    for (int j = 0; j < k->n_fields; j++) {
        if (k->held[j] < 0 ||
            field_at(frame + V2_HEADER, frame[1], k->at[j], k->size[j]) != k->held[j]) {
            return 0;
        }
    }
    return 1;
}

/* The run as its tuple (NULL: no memory). */
static PyObject *run_tuple(const Run *run) {
    PyObject *counts = PyTuple_New(run->n_kinds * 2);
    PyObject *kept = NULL;
    int n_kept = 0;
    for (int i = 0; i < MAX_KEPT; i++) {
        n_kept += run->kept_len[i] > 0;
    }
    if (counts != NULL) {
        kept = PyTuple_New(n_kept * 2);
    }
    if (kept == NULL) {
        Py_XDECREF(counts);
        return NULL;
    }
    for (int i = 0; i < run->n_kinds; i++) {
        PyTuple_SET_ITEM(counts, i * 2, PyLong_FromUnsignedLong(run->ids[i]));
        PyTuple_SET_ITEM(counts, i * 2 + 1, PyLong_FromLong(run->counts[i]));
    }
    int j = 0;
    for (int i = 0; i < MAX_KEPT; i++) {
        if (run->kept_len[i] > 0) {
            PyTuple_SET_ITEM(kept, j * 2,
                             PyBytes_FromStringAndSize((const char *)run->kept[i], run->kept_len[i]));
            PyTuple_SET_ITEM(kept, j * 2 + 1, PyFloat_FromDouble(run->kept_at[i]));
            j++;
        }
    }
    if (PyErr_Occurred()) {
        Py_DECREF(counts);
        Py_DECREF(kept);
        return NULL;
    }
    return Py_BuildValue("(dddllliLdNN)", run->first_at, run->last_at, run->max_gap, run->frames,
                         run->datagrams, run->bytes, run->last_seq, run->boot_max,
                         run->boot_max_at, counts, kept);
}

/* Ends the open run, if any, as an entry of ``out`` (room for one reserved); -1: no memory. */
static int run_close(Run *run, Entries *out, unsigned char *routed) {
    if (!run->open) {
        return 0;
    }
    run->open = 0;
    PyObject *tuple = run_tuple(run);
    if (tuple == NULL) {
        return -1;
    }
    Entry e = {.data = NULL, .sender = NULL, .stamp = NAN, .run = tuple};
    routed[out->count] = 1;
    out->items[out->count++] = e;
    return 0;
}

/* Whether a routed datagram of ``count`` frames may join a run (else it goes whole; *stop:
 * and no more runs this call); the tilt class moves on with each ATTITUDE either way. */
static int joins_run(RunRules *r, const unsigned char *d, int count, const Py_ssize_t *starts,
                     const long long *summary, double arrived, long long *boot_high,
                     int *stop) {
    int joins = 1;
    for (int i = 0; i < count; i++) {
        unsigned int id = (unsigned int)summary[i * 3];
        long long boot = summary[i * 3 + 2];
        if (id == r->heartbeat_id) {
            *stop = 1;
            joins = 0;
        }
        if (boot >= 0) {
            if (*boot_high >= 0 && boot < *boot_high - r->backstep) {
                *stop = 1; /* a reboot claim: Python settles it frame by frame */
                return 0;
            }
            if (boot > *boot_high) {
                *boot_high = boot;
            }
        }
        if (id == r->attitude_id) {
            int tilt = tilt_class_of(d + starts[i], r);
            if (tilt != r->tilt_class) {
                *stop = 1; /* Python sees the change at once */
                joins = 0;
                r->tilt_class = tilt;
            }
        }
        for (int k = 0; k < r->n_states; k++) {
            if (r->states[k].id != id) {
                continue;
            }
            if (!state_holds(&r->states[k], d + starts[i])) {
                *stop = 1; /* a new state: Python reads it, and at once */
                joins = 0;
            } else if (arrived >= r->window_end) {
                joins = 0; /* read whole, it would see the rate window close */
            }
        }
        if (!in_bitmap(r->kinds, r->kinds_bytes, id)) {
            joins = 0;
        }
    }
    return joins;
}

static void run_add(Run *run, const RunRules *r, const unsigned char *d, int count,
                    const Py_ssize_t *starts, const Py_ssize_t *ends, const long long *summary,
                    double at, Py_ssize_t size) {
    if (!run->open) {
        memset(run, 0, sizeof *run);
        run->open = 1;
        run->first_at = run->last_at = at;
        run->boot_max = -1;
    }
    double gap = at - run->last_at;
    if (gap > run->max_gap) {
        run->max_gap = gap;
    }
    run->last_at = at;
    run->datagrams++;
    run->bytes += (long)size;
    for (int i = 0; i < count; i++) {
        unsigned int id = (unsigned int)summary[i * 3];
        long long boot = summary[i * 3 + 2];
        int k = 0;
        while (k < run->n_kinds && run->ids[k] != id) {
            k++;
        }
        if (k == run->n_kinds) { /* room checked by the caller */
            run->ids[k] = id;
            run->counts[k] = 0;
            run->n_kinds++;
        }
        run->counts[k]++;
        run->frames++;
        run->last_seq = (int)summary[i * 3 + 1];
        if (boot > run->boot_max) {
            run->boot_max = boot;
            run->boot_max_at = at;
        }
        for (int j = 0; j < r->n_kept; j++) {
            Py_ssize_t length = ends[i] - starts[i];
            if (r->kept_ids[j] == id && length <= FRAME_MAX) {
                memcpy(run->kept[j], d + starts[i], (size_t)length);
                run->kept_len[j] = (int)length;
                run->kept_at[j] = at;
            }
        }
    }
}

/* Whether adding a datagram of these frames would overflow the run's table of ids. */
static int run_full(const Run *run, int count, const long long *summary) {
    if (!run->open) {
        return 0;
    }
    int more = 0;
    for (int i = 0; i < count; i++) {
        unsigned int id = (unsigned int)summary[i * 3];
        int k = 0;
        while (k < run->n_kinds && run->ids[k] != id) {
            k++;
        }
        more += k == run->n_kinds;
    }
    return run->n_kinds + more > RUN_KINDS;
}

static PyObject *pump(PyObject *module, PyObject *args) {
    (void)module;
    int bulk_fd, urgent_fd, sysid, compid, agent_comp, log_busy, urgent_returns;
    double timeout_s, due_s, age_s, offset, boot_due_s, boot_age_s;
    PyObject *wake_list, *client_list, *locked_obj, *held_in, *runs_in;
    Py_ssize_t limit, routine_bytes;
    const char *routine;
    if (!PyArg_ParseTuple(args, "iiO(dddddd)OOiiippOny#O:pump", &bulk_fd, &urgent_fd,
                          &wake_list, &timeout_s, &due_s, &age_s, &offset, &boot_due_s,
                          &boot_age_s, &client_list, &locked_obj,
                          &sysid, &compid, &agent_comp, &log_busy, &urgent_returns, &held_in,
                          &limit, &routine, &routine_bytes, &runs_in)) {
        return NULL;
    }
    RunRules runs;
    if (parse_run_rules(runs_in, &runs) < 0) {
        return NULL;
    }
    if (ensure_slots() < 0) {
        return NULL;
    }
    /* as many wake descriptors and clients as the caller gives (the hub sets its own
     * limit on clients): none is left out */
    struct pollfd *fds = NULL;
    Client *clients = NULL;
    Entries held = {0}, fresh = {0}, out = {0}, spent = {0};
    Outbox box;
    box.count = 0;
    unsigned char *routed = NULL;
    Py_ssize_t routed_size = 0;
    Run *run = NULL;
    Arena arena = {0};
    /* Routing needs no GIL: it is released for the wait, and taken again only when Python
     * objects are made (an entry Python is to see, a run closed) or at the return. So
     * while the stream flows in runs the reader takes no lock at each datagram, and the
     * agent's other threads get the interpreter without asking this one. */
    PyThreadState *released = NULL;
#define HOLD_GIL()                               \
    do {                                         \
        if (released != NULL) {                  \
            PyEval_RestoreThread(released);      \
            released = NULL;                     \
        }                                        \
    } while (0)
    int failed_errno = 0; /* a failed system call, said with the GIL at the end */
    PyObject *result = NULL;
    Py_ssize_t wakes = PySequence_Size(wake_list);
    Py_ssize_t given = wakes < 0 ? -1 : PySequence_Size(client_list);
    if (given < 0) {
        return NULL;
    }
    fds = PyMem_Malloc(sizeof(struct pollfd) * (size_t)(2 + wakes));
    clients = PyMem_Malloc(sizeof(Client) * (size_t)(given > 0 ? given : 1));
    if (fds == NULL || clients == NULL) {
        PyErr_NoMemory();
        goto fail;
    }
    int nfds = 0;
    fds[nfds++] = (struct pollfd){.fd = bulk_fd, .events = POLLIN};
    if (urgent_fd >= 0) {
        fds[nfds++] = (struct pollfd){.fd = urgent_fd, .events = POLLIN};
    }
    int wake_at = nfds;
    for (Py_ssize_t i = 0; i < wakes; i++) {
        PyObject *item = PySequence_GetItem(wake_list, i);
        if (item == NULL) {
            goto fail;
        }
        int fd = (int)PyLong_AsLong(item);
        Py_DECREF(item);
        if (fd == -1 && PyErr_Occurred()) {
            goto fail;
        }
        fds[nfds++] = (struct pollfd){.fd = fd, .events = POLLIN};
    }
    int n_clients = 0;
    for (Py_ssize_t i = 0; i < given; i++) {
        PyObject *item = PySequence_GetItem(client_list, i);
        if (item == NULL) {
            goto fail;
        }
        PyObject *where;
        int ok = PyArg_ParseTuple(item, "iO", &clients[n_clients].fd, &where) &&
                 address_of(where, &clients[n_clients].address) == 0;
        Py_DECREF(item);
        if (!ok) {
            goto fail;
        }
        n_clients++;
    }
    struct sockaddr_in locked;
    memset(&locked, 0, sizeof locked);
    if (locked_obj != Py_None && address_of(locked_obj, &locked) < 0) {
        goto fail;
    }
    Rules rules = {sysid, compid, agent_comp, log_busy, (const unsigned char *)routine,
                   routine_bytes};

    /* what the caller held from before */
    Py_ssize_t n_held = PySequence_Size(held_in);
    if (n_held < 0) {
        goto fail;
    }
    for (Py_ssize_t i = 0; i < n_held; i++) {
        PyObject *item = PySequence_GetItem(held_in, i);
        if (item == NULL) {
            goto fail;
        }
        PyObject *data, *from, *when;
        if (!PyArg_ParseTuple(item, "OOO", &data, &from, &when)) {
            Py_DECREF(item);
            goto fail;
        }
        if (!PyBytes_Check(data)) {
            Py_DECREF(item);
            PyErr_SetString(PyExc_TypeError, "a held datagram is bytes");
            goto fail;
        }
        Entry e = {.data = Py_NewRef(data),
                   .sender = Py_NewRef(from),
                   .stamp = when == Py_None ? NAN : PyFloat_AsDouble(when),
                   .locked = from == locked_obj && locked_obj != Py_None};
        Py_DECREF(item);
        if (push(&held, e) < 0) {
            Py_DECREF(e.data);
            Py_DECREF(e.sender);
            goto fail;
        }
    }

    int forwarding = n_clients > 0 && locked_obj != Py_None;
    run = runs.on ? PyMem_RawCalloc(1, sizeof(Run)) : NULL;
    if (runs.on && run == NULL) {
        PyErr_NoMemory();
        goto fail;
    }
    int running = runs.on; /* runs may still be taken this call */
    long long boot_high = runs.boot_max;
    double last_arrived = -INFINITY;
    int woke = 0, done = 0, looks_after_hold = 0, looked_once = 0;
    double started = monotonic();
    double hard = started + (timeout_s > 0 ? timeout_s : 0);
    double due = started + (due_s > 0 ? due_s : 0); /* moves with arrivals (age_s >= 0) */
    /* frozen telemetry's deadline: moves with each frame whose time_boot_ms advances
     * (boot_age_s >= 0, while runs are taken: the tracker's highest is known) */
    int boot_moves = boot_age_s >= 0 && runs.on;
    double boot_due = boot_moves ? started + (boot_due_s > 0 ? boot_due_s : 0) : INFINITY;
    double deadline = fmin(fmin(due, boot_due), hard);
    while (!done) {
        int ready_data = 0;
        /* which sockets to read: both after a hold, else those poll found readable (a
         * read of an empty socket is a system call for nothing, at every datagram) */
        int read_urgent = urgent_fd >= 0, read_bulk = 1;
        double polled_at = INFINITY;
        if (held.count > 0 && looks_after_hold < 2) {
            ready_data = 1; /* one more look at once, as the Python reader takes */
            looks_after_hold++;
        } else {
            double now = monotonic();
            if (looked_once && held.count == 0 && now >= deadline) {
                break; /* past the deadline after a look: the decision loop is due */
            }
            double left = deadline - now;
            int wait_ms = left > 0 ? (int)ceil(left * 1000) : 0;
            int polled;
            if (released == NULL) {
                released = PyEval_SaveThread();
            }
            polled = poll(fds, (nfds_t)nfds, wait_ms);
            if (polled < 0) {
                if (errno == EINTR) {
                    HOLD_GIL();
                    if (PyErr_CheckSignals() < 0) {
                        goto fail;
                    }
                    continue;
                }
                failed_errno = errno;
                goto fail;
            }
            if (polled == 0) {
                break; /* timed out: the decision loop is due */
            }
            for (int i = wake_at; i < nfds; i++) {
                if (fds[i].revents) {
                    woke = 1;
                }
            }
            for (int i = 0; i < wake_at; i++) {
                if (fds[i].revents) {
                    ready_data = 1;
                }
            }
            polled_at = realtime();
            read_bulk = fds[0].revents != 0;
            read_urgent = urgent_fd >= 0 && fds[1].revents != 0;
            if (fds[0].revents & (POLLERR | POLLNVAL) ||
                (urgent_fd >= 0 && fds[1].revents & (POLLERR | POLLNVAL))) {
                done = 1; /* the reads tell Python what failed */
            }
            if (woke) {
                /* Python looks again after this read (a call, another link's answer, the
                 * hub's clients changed): what is read with it goes whole, not in a run a
                 * route made for other clients would have routed alone */
                done = 1;
                running = 0;
            }
        }
        if (ready_data) {
            /* What arrived after poll looked may be newer than something then queued on
             * a socket not read now: it is held for the next look (as below). */
            looked_once = 1;
            double cutoff = isfinite(polled_at) ? polled_at : realtime();
            int got_urgent = 0, got_bulk = 0;
            /* every entry is routed or made by now: the arena's bytes are free again */
            arena.used = 0;
            const struct sockaddr_in *lock = locked_obj != Py_None ? &locked : NULL;
            if (read_urgent) {
                got_urgent = read_socket(urgent_fd, BATCH * 4, 1, lock, &fresh, &arena);
                if (got_urgent < 0) {
                    failed_errno = got_urgent == -1 ? errno : 0;
                    goto fail;
                }
                if (got_urgent >= BATCH * 4) {
                    cutoff = fmin(cutoff, arrival(&fresh.items[fresh.count - 1]));
                }
            }
            if (read_bulk) {
                got_bulk = read_socket(bulk_fd, BATCH * 4, 0, lock, &fresh, &arena);
                if (got_bulk < 0) {
                    failed_errno = got_bulk == -1 ? errno : 0;
                    goto fail;
                }
            }
            if (urgent_fd >= 0 && got_bulk >= BATCH * 4) {
                cutoff = fmin(cutoff, arrival(&fresh.items[fresh.count - 1]));
            }
            double looked = realtime();
            /* merge what was held with what was read, by arrival (room first: moving
             * an entry must not fail halfway) */
            if (reserve(&fresh, held.count) < 0) {
                goto fail;
            }
            memcpy(fresh.items + fresh.count, held.items, sizeof(Entry) * (size_t)held.count);
            fresh.count += held.count;
            held.count = 0;
            /* one more in out: a run ending with or after these */
            if (reserve(&held, fresh.count) < 0 || reserve(&out, fresh.count + 1) < 0 ||
                reserve(&spent, fresh.count) < 0) {
                goto fail;
            }
            void *routed_room = routed;
            if (grow(&routed_room, &routed_size, out.count + fresh.count + 1, 1, 64) < 0) {
                goto fail;
            }
            routed = routed_room;
            if (fresh.count > 1) {
                qsort(fresh.items, (size_t)fresh.count, sizeof(Entry), compare_entries);
            }
            Py_ssize_t moved = fresh.count;
            fresh.count = 0; /* every entry goes to held or out below */
            for (Py_ssize_t i = 0; i < moved; i++) {
                Entry *e = &fresh.items[i];
                int later = urgent_fd >= 0 && !isnan(e->stamp) && cutoff < e->stamp &&
                            e->stamp <= looked;
                if (later) {
                    /* made now: the arena's bytes are reused by the next read */
                    HOLD_GIL();
                    if (make(e, &arena, locked_obj) < 0) {
                        fresh.items[fresh.count++] = *e; /* cleared at the end */
                        goto fail;
                    }
                    held.items[held.count++] = *e;
                    continue;
                }
                int sent = 0, in_run = 0;
                /* an urgent datagram while urgent ones may not end the call (the short
                 * interval after an early return: a flood of them wakes no one more
                 * often than the unhurried reader wakes) */
                int held_back = e->urgent && !urgent_returns;
                PyObject *summarised = NULL;
                int from_locked = e->locked;
                double arrived = isnan(e->stamp) ? monotonic() : e->stamp - offset;
                if (arrived < last_arrived) {
                    arrived = last_arrived; /* as Python's: never before an earlier one */
                }
                last_arrived = arrived;
                if (forwarding && from_locked) {
                    Py_ssize_t starts[MAX_FRAMES], ends[MAX_FRAMES];
                    long long summary[MAX_FRAMES * 3];
                    int routine = 0;
                    Py_ssize_t size;
                    const unsigned char *d = bytes_of(e, &arena, &size);
                    int count = frames_of(d, size, &rules, starts, ends, &routine, summary);
                    if (count > 0) {
                        forward(&box, d, count, starts, ends, clients, n_clients);
                        sent = 1;
                        long long boot_before = boot_high;
                        if (running) {
                            int stop = 0;
                            int joins = joins_run(&runs, d, count, starts, summary, arrived,
                                                  &boot_high, &stop);
                            running = !stop;
                            if (stop && !held_back) {
                                done = 1; /* Python reads what stopped them at once */
                            }
                            if (joins && !(e->urgent && urgent_returns)) {
                                if (run->open && (arrived - run->last_at >= runs.gap_limit ||
                                                  run_full(run, count, summary))) {
                                    HOLD_GIL();
                                    if (run_close(run, &out, routed) < 0) {
                                        goto fail;
                                    }
                                }
                                run_add(run, &runs, d, count, starts, ends, summary, arrived, size);
                                in_run = 1;
                            }
                        }
                        if (!in_run && routine) {
                            /* without it (no memory), Python reads the frames themselves */
                            HOLD_GIL();
                            summarised = summarise(summary, count);
                            if (summarised == NULL) {
                                PyErr_Clear();
                            }
                        }
                        if (age_s >= 0 && arrived + age_s > due) {
                            due = arrived + age_s; /* its last message is this one now */
                        }
                        if (boot_moves && boot_high > boot_before) {
                            /* time_boot_ms advanced (joins_run keeps the highest) */
                            boot_due = fmax(boot_due, arrived + boot_age_s);
                        }
                        deadline = fmin(fmin(due, boot_due), hard);
                    } else {
                        /* Python must see it now, and forwards it and what follows */
                        forwarding = 0;
                        running = 0;
                        done = 1;
                    }
                }
                if (!in_run && sent && runs.on && !held_back) {
                    done = 1; /* while runs are taken, what Python reads whole is read now */
                }
                if (!in_run) {
                    /* what Python reads whole comes after the run before it */
                    HOLD_GIL();
                    if ((runs.on && run_close(run, &out, routed) < 0) ||
                        make(e, &arena, locked_obj) < 0) {
                        Py_XDECREF(summarised);
                        fresh.items[fresh.count++] = *e; /* cleared at the end */
                        goto fail;
                    }
                    e->frames = summarised;
                    out.items[out.count++] = *e;
                    routed[out.count - 1] = (unsigned char)sent;
                } else {
                    spent.items[spent.count++] = *e; /* its bytes go out at the flush */
                }
                if (running && from_locked && arrived >= runs.window_end) {
                    /* the tracker's rate window closes at this message, and may learn
                     * another silence threshold: Python takes it now */
                    running = 0;
                    done = 1;
                    if (in_run) {
                        HOLD_GIL();
                        if (run_close(run, &out, routed) < 0) {
                            goto fail;
                        }
                    }
                }
                if (e->urgent && urgent_returns) {
                    done = 1;
                }
            }
            flush(&box, clients, n_clients); /* the data stays alive in out until the return */
            for (Py_ssize_t i = 0; i < spent.count; i++) { /* in a run: sent, and done with */
                if (spent.items[i].data != NULL || spent.items[i].sender != NULL) {
                    HOLD_GIL(); /* one held from before: made */
                    Py_CLEAR(spent.items[i].data);
                    Py_CLEAR(spent.items[i].sender);
                }
            }
            spent.count = 0;
            if (held.count == 0) {
                looks_after_hold = 0;
            }
            if (out.count >= limit) {
                done = 1;
            }
        }
    }

    HOLD_GIL();
    if (runs.on && run->open) {
        if (reserve(&out, 1) < 0) {
            goto fail;
        }
        void *routed_room = routed;
        if (grow(&routed_room, &routed_size, out.count + 1, 1, 64) < 0) {
            goto fail;
        }
        routed = routed_room;
        if (run_close(run, &out, routed) < 0) {
            goto fail;
        }
    }
    {
        PyObject *items = PyList_New(out.count);
        PyObject *held_out = items == NULL ? NULL : PyList_New(held.count);
        if (held_out == NULL) {
            Py_XDECREF(items);
            goto fail;
        }
        for (Py_ssize_t i = 0; i < out.count; i++) {
            PyObject *t = entry_tuple(&out.items[i], routed[i]);
            if (t == NULL) {
                Py_DECREF(items);
                Py_DECREF(held_out);
                goto fail;
            }
            PyList_SET_ITEM(items, i, t);
        }
        for (Py_ssize_t i = 0; i < held.count; i++) {
            PyObject *t = entry_tuple(&held.items[i], -1);
            if (t == NULL) {
                Py_DECREF(items);
                Py_DECREF(held_out);
                goto fail;
            }
            PyList_SET_ITEM(held_out, i, t);
        }
        result = Py_BuildValue("(NNO)", items, held_out, woke ? Py_True : Py_False);
    }
fail:
    HOLD_GIL();
#undef HOLD_GIL
    if (result == NULL && !PyErr_Occurred()) {
        if (failed_errno != 0) {
            errno = failed_errno;
            PyErr_SetFromErrno(PyExc_OSError);
        } else {
            PyErr_NoMemory(); /* what else fails without saying */
        }
    }
    clear(&held);
    clear(&out);
    clear(&fresh);
    clear(&spent);
    PyMem_RawFree(arena.bytes);
    PyMem_RawFree(routed);
    PyMem_RawFree(run);
    PyMem_Free(clients);
    PyMem_Free(fds);
    return result;
}

static PyMethodDef methods[] = {
    {"receive", receive, METH_VARARGS,
     "receive(fd, limit) -> [(data, (host, port) | None, stamp | None)]: up to limit "
     "queued datagrams, one recvmmsg per 16."},
    {"send", send_datagram, METH_VARARGS,
     "send(fd, data, (host, port)): one datagram, the GIL held (MSG_DONTWAIT)."},
    {"set_messages", set_messages, METH_O,
     "set_messages({msg_id: (crc_extra, target_system_at, target_component_at)})"},
    {"pump", pump, METH_VARARGS,
     "pump(bulk_fd, urgent_fd, wake_fds, (timeout_s, due_s, age_s, offset, boot_due_s, "
     "boot_age_s), clients, locked, sysid, compid, "
     "agent_comp, log_busy, urgent_returns, held, limit, routine, runs) -> (items, held, woke)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "roost_agent._udpbatch",
    "Batch UDP reception (recvmmsg, kernel arrival stamps) and a send that keeps the GIL "
    "for the agent's links, and the hub's fast path: the active autopilot's frames to "
    "plain UDP clients in C.",
    -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__udpbatch(void) { return PyModule_Create(&module); }
