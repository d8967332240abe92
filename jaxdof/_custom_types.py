"""Array type aliases used in every signature (shapes are checked by the jaxtyping pytest hook).

The `...Like` aliases annotate inputs at the public boundary. Their dimensions are prefixed with
`_` (documented, not enforced) and their dtype is `Shaped`, so that a wrong shape or dtype reaches
our own checks, whose messages say what is wrong and how to fix it.
"""

from jaxtyping import Array, ArrayLike, Float, Shaped


#: A linear-light image, `(H, W)` or `(H, W, C)`.
Image = Float[Array, "h w *c"]
ImageLike = Shaped[ArrayLike, "_h _w *_c"]
#: Z-depth along the optical axis in metres, `(H, W)`; `inf` is allowed.
Depth = Float[Array, "h w"]
DepthLike = Shaped[ArrayLike, "_h _w"]
#: Circle-of-confusion radius in pixels, `(H, W)`.
Radius = Float[Array, "h w"]
RadiusLike = Shaped[ArrayLike, "_h _w"]
#: A scalar, or an array of any shape that broadcasts with its partners.
ScalarLike = Float[ArrayLike, ""]
AnyFloat = Float[Array, "..."]
AnyFloatLike = Shaped[ArrayLike, "..."]
