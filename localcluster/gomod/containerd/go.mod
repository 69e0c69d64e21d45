// Wrapper module that pins containerd (the container runtime of the harness's real nodes,
// as in K3s): containerd, ctr and containerd-shim-runc-v2 are built from it by
// localcluster/build-node.sh.
module roost.dev/tests/containerd

go 1.26.6

require github.com/containerd/containerd/v2 v2.4.2 // indirect
