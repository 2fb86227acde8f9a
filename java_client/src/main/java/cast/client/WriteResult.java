package cast.client;

/**
 * The result of one write.
 *
 * @param revision the working memory's revision of this write
 * @param version the entry's version after the write (0 after an add)
 */
public record WriteResult(long revision, long version) {}
