/* Batch reception for the agent's UDP links: recvmmsg with kernel arrival stamps.
 *
 * Why: with a hub client connected the link reader wakes for every datagram, and read in
 * Python each wake-up cost a recvmsg per datagram (its ancillary data parsed into a list
 * of tuples and a struct), then one more recvmsg that fails with EAGAIN and raises
 * BlockingIOError (an exception object and its message built, then caught). Here one
 * system call takes every queued datagram (up to BATCH at a time) and an empty queue is
 * an empty list. roost_agent.transport falls back to the Python reads where this module
 * is not built (an editable install); both give the same (data, sender, stamp) triples.
 *
 * receive(fd, limit) -> list of (bytes, (host, port) | None, float | None): up to
 * ``limit`` datagrams in arrival order; the stamp is the kernel's CLOCK_REALTIME arrival
 * time (SO_TIMESTAMPNS) in seconds, None when the socket does not ask for it. Empty
 * datagrams carry nothing and are skipped. OSError for a failure other than an empty
 * queue or a refused earlier send (ECONNREFUSED, which the Python reads also ignore).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <arpa/inet.h>
#include <errno.h>
#include <netinet/in.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>

#define BATCH 16
#define SLOT 65536 /* a UDP datagram's payload is at most 65,507 bytes: never truncated */
#define CONTROL 64 /* room for one timespec control message, as the Python read asks */

static char *slots; /* BATCH * SLOT, allocated on first use; only touched pages count */

static PyObject *sender(const struct sockaddr_in *address, socklen_t length) {
    char host[INET_ADDRSTRLEN];
    if (length < sizeof(struct sockaddr_in) || address->sin_family != AF_INET ||
        inet_ntop(AF_INET, &address->sin_addr, host, sizeof host) == NULL) {
        Py_RETURN_NONE;
    }
    return Py_BuildValue("(si)", host, (int)ntohs(address->sin_port));
}

static PyObject *stamp(struct msghdr *header) {
    for (struct cmsghdr *c = CMSG_FIRSTHDR(header); c != NULL; c = CMSG_NXTHDR(header, c)) {
        if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SCM_TIMESTAMPNS &&
            c->cmsg_len >= CMSG_LEN(sizeof(struct timespec))) {
            struct timespec ts;
            memcpy(&ts, CMSG_DATA(c), sizeof ts);
            return PyFloat_FromDouble((double)ts.tv_sec + (double)ts.tv_nsec * 1e-9);
        }
    }
    Py_RETURN_NONE;
}

static PyObject *receive(PyObject *module, PyObject *args) {
    (void)module;
    int fd;
    Py_ssize_t limit;
    if (!PyArg_ParseTuple(args, "in:receive", &fd, &limit)) {
        return NULL;
    }
    if (slots == NULL) {
        slots = PyMem_RawMalloc((size_t)BATCH * SLOT);
        if (slots == NULL) {
            return PyErr_NoMemory();
        }
    }
    PyObject *out = PyList_New(0);
    if (out == NULL) {
        return NULL;
    }
    struct mmsghdr messages[BATCH];
    struct iovec vectors[BATCH];
    struct sockaddr_in addresses[BATCH];
    union {
        char bytes[CONTROL];
        struct cmsghdr align;
    } controls[BATCH];
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
            Py_DECREF(out);
            return PyErr_SetFromErrno(PyExc_OSError);
        }
        for (int i = 0; i < got; i++) {
            struct msghdr *h = &messages[i].msg_hdr;
            if (messages[i].msg_len == 0) {
                continue;
            }
            PyObject *data = PyBytes_FromStringAndSize(slots + (size_t)i * SLOT,
                                                       (Py_ssize_t)messages[i].msg_len);
            PyObject *from = data == NULL ? NULL : sender(&addresses[i], h->msg_namelen);
            PyObject *when = from == NULL ? NULL : stamp(h);
            PyObject *item = when == NULL ? NULL : PyTuple_Pack(3, data, from, when);
            Py_XDECREF(data);
            Py_XDECREF(from);
            Py_XDECREF(when);
            if (item == NULL || PyList_Append(out, item) < 0) {
                Py_XDECREF(item);
                Py_DECREF(out);
                return NULL;
            }
            Py_DECREF(item);
        }
        limit -= got;
        if ((unsigned int)got < want) {
            break; /* the queue is empty now: no read that fails to say so */
        }
    }
    return out;
}

static PyMethodDef methods[] = {
    {"receive", receive, METH_VARARGS,
     "receive(fd, limit) -> [(data, (host, port) | None, stamp | None)]: up to limit "
     "queued datagrams, one recvmmsg per 16."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "roost_agent._udpbatch",
    "Batch UDP reception (recvmmsg, kernel arrival stamps) for the agent's links.", -1,
    methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__udpbatch(void) { return PyModule_Create(&module); }
