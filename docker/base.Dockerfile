# The local Python base image: the root filesystem docker/build-base.sh makes from Debian's
# own packages, as one layer. It stands in for the public Python base on machines that can
# reach Debian's archive but no container registry; docker/Dockerfile takes either.
FROM scratch
ADD rootfs.tar /
ENV LANG=C.UTF-8
CMD ["python3"]
