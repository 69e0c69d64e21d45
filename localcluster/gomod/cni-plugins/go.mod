// Wrapper module that pins the CNI reference plugins (bridge, host-local, loopback,
// portmap) the harness's real nodes use for pod networking; built by
// localcluster/build-node.sh.
module roost.dev/tests/cniplugins

go 1.25.0

require github.com/containernetworking/plugins v1.9.1 // indirect
