/* The pod sandbox process of the harness's real nodes: it holds the pod's namespaces open,
 * reaps orphaned children (it is PID 1 when the pod shares its PID namespace) and exits
 * cleanly on SIGINT or SIGTERM. Built statically by pause-image.sh into a FROM-scratch
 * image, because no registry with the upstream pause image is reachable from the harness. */
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <unistd.h>

static void stop(int sig) {
  (void)sig;
  _exit(0);
}

static void reap(int sig) {
  (void)sig;
  while (waitpid(-1, NULL, WNOHANG) > 0) {
  }
}

static void on(int sig, void (*handler)(int)) {
  struct sigaction action;
  memset(&action, 0, sizeof action);
  action.sa_handler = handler;
  action.sa_flags = SA_RESTART;
  sigemptyset(&action.sa_mask);
  if (sigaction(sig, &action, NULL) != 0) {
    perror("sigaction");
    exit(1);
  }
}

int main(int argc, char **argv) {
  if (argc > 1 && strcmp(argv[1], "-v") == 0) {
    puts("roost-pause");
    return 0;
  }
  if (getpid() != 1) {
    fputs("roost-pause: not PID 1; orphans of the pod are not reaped here\n", stderr);
  }
  puts("roost-pause: holding the pod's namespaces");
  fflush(stdout);
  on(SIGINT, stop);
  on(SIGTERM, stop);
  on(SIGCHLD, reap);
  for (;;) {
    pause();
  }
}
